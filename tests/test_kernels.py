"""The compiled path-tracing kernels against the numpy reference functions they replace."""

import itertools

import numpy as np
import pytest

from isolume.baking import kernels, rng, sampling_kernels, sky_kernels
from isolume.baking.lattice import LUMINANCE
from isolume.baking.sampling import sample_cosine_hemisphere, to_world


@pytest.fixture(scope="module")
def normals():
    n = np.random.default_rng(1).normal(size=(20000, 3))
    n[:4] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1e-7, -1]]  # poles and a near-pole
    return (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)


def test_uniforms_equal_numpy_bit_for_bit():
    keys = rng.path_keys(7, np.arange(5000), np.arange(5000) % 13)
    for dim in (0, 1, 6, 1000):
        np.testing.assert_array_equal(sampling_kernels.uniform2(keys, dim), rng.uniform2(keys, dim))


def test_31_bit_and_single_precision_uniforms_match_the_uniform():
    keys = rng.path_keys(11, np.arange(20000), np.arange(20000) % 7)
    k0 = sampling_kernels.dimension_key(3)
    got = np.array([sampling_kernels.uniform_f32(k, k0) for k in keys], np.float64)
    np.testing.assert_allclose(got, rng.uniform(keys, 3), rtol=2**-23, atol=2**-31)
    got31 = np.array([sampling_kernels.uniform31(k, k0) for k in keys])
    assert np.all((rng.uniform(keys, 3) - got31 >= 0) & (rng.uniform(keys, 3) - got31 < 2**-31))
    assert got.max() < 1.0 and got.min() >= 0.0
    # a key whose hash is within 2^7 of 2^32, where rounding to float32 would give 1
    for start in range(0, 2**32, 2**24):
        x = np.arange(start, start + 2**24, dtype=np.uint32)
        near_one = x[rng.pcg_hash(x) >= np.uint32(2**32 - 128)]
        if len(near_one):
            break
    assert sampling_kernels.uniform_f32(near_one[0], np.uint32(0)) == np.float32(1 - 2**-24)


def test_path_starts_gather_keys_and_first_directions():
    ids = np.array([3, 17, 99, 4_000_000_000 % 2**32, 12], np.int64)
    pos = np.array([0, 0, 1, 3, 3, 3, 4], np.int64)
    samples = np.array([0, 1, 7, 2, 3, 4, 9], np.int64)
    texels = np.array([0, 1, 3, 4], np.int64)
    origins = np.arange(12, dtype=np.float32).reshape(4, 3)
    normals = np.array([[0, 0, 1], [0, 1, 0], [0.6, 0, -0.8], [-1, 0, 0]], np.float32)
    keys, o, n, dirs = kernels.path_starts(np.uint32(rng.seed_key(42)), ids, pos, samples,
                                           texels, origins, normals)
    np.testing.assert_array_equal(keys, rng.path_keys(42, ids[pos], samples))
    rows = np.searchsorted(texels, pos)
    assert o.shape == n.shape == dirs.shape == (3, len(pos))
    np.testing.assert_array_equal(o.T, origins[rows])
    np.testing.assert_array_equal(n.T, normals[rows])
    np.testing.assert_array_equal(dirs, kernels.cosine_directions(keys, 0, n))
    # a later chunk of the same paths, with all the texels' start points
    late = kernels.path_starts(np.uint32(rng.seed_key(42)), ids, pos[3:], samples[3:],
                               texels, origins, normals)
    for got, whole in zip(late, (keys, o, n, dirs), strict=True):
        np.testing.assert_array_equal(got, whole[..., 3:])


def test_level_paths_match_the_numpy_expansion():
    """The pending paths of each level (`level_texels`, then `texel_paths` of all its
    texels and of any run of them, by index into the run): as
    `reference.pending_samples` and `Plan.on_upper` lay them out (expand every texel's
    pending samples, keep those on this level, sort by texel)."""
    from isolume.baking.plan import GOLDEN_FRACTION
    from isolume.baking.reference import pending_samples

    gen = np.random.default_rng(4)
    count = 300
    lower = gen.integers(0, 5, count)
    phase = gen.integers(0, 2**32, count, dtype=np.uint32)
    weight = gen.random(count)
    weight[:20] = 0.0  # texels with one level only
    done = gen.integers(0, 40, count)
    remaining = gen.integers(0, 9, count)
    positions = np.arange(count)
    for level in range(6):
        here = positions[lower == level]
        below = positions[lower == level - 1]
        texels, goes_up, counts = kernels.level_texels(here, below, done, remaining, phase,
                                                       weight, GOLDEN_FRACTION)
        index, samples, strata = kernels.texel_paths(texels, goes_up, counts, done, remaining,
                                             phase, weight, GOLDEN_FRACTION)
        pos = texels[index]
        want_pos, want_samples = [], []
        for group, on_upper in ((here, False), (below, True)):
            p, s = pending_samples(group, done, remaining)
            upper = np.mod(phase[p] / 2.0**32 + s * GOLDEN_FRACTION, 1.0) < weight[p]
            want_pos.append(p[upper == on_upper])
            want_samples.append(s[upper == on_upper])
        p, s = np.concatenate(want_pos), np.concatenate(want_samples)
        order = np.argsort(p, kind="stable")
        np.testing.assert_array_equal(pos, p[order])
        np.testing.assert_array_equal(samples, s[order])
        np.testing.assert_array_equal(texels, np.unique(p))
        np.testing.assert_array_equal(counts, np.unique(p, return_counts=True)[1])
        np.testing.assert_array_equal(goes_up, np.isin(texels, below))
        up = goes_up[index]
        ranks = [np.count_nonzero((np.mod(phase[q] / 2.0**32 + np.arange(t) * GOLDEN_FRACTION,
                                          1.0) < weight[q]) == u)
                 for q, t, u in zip(pos, samples, up, strict=True)]
        np.testing.assert_array_equal(strata, 2 * np.asarray(ranks, np.int64) + up)
        cut = len(texels) // 3  # a run of texels: the same paths as the whole level's
        start = counts[:cut].sum()
        part = kernels.texel_paths(texels[cut:], goes_up[cut:], counts[cut:], done, remaining,
                                   phase, weight, GOLDEN_FRACTION)
        np.testing.assert_array_equal(texels[cut:][part[0]], pos[start:])
        np.testing.assert_array_equal(part[1], samples[start:])
        np.testing.assert_array_equal(part[2], strata[start:])


def test_chunks_are_whole_texels_of_guided_size():
    """`passes.chunk_bounds`: consecutive runs of whole texels covering the level; each
    holds at least the guided size (1/(2·w) of the paths left, w the workers but at least
    GUIDED_WORKERS, clamped to MIN_PATHS_PER_CHUNK … PATHS_PER_CHUNK) and stops at the
    first texel that reaches it."""
    from isolume.baking.passes import (
        GUIDED_WORKERS,
        MIN_PATHS_PER_CHUNK,
        PATHS_PER_CHUNK,
        chunk_bounds,
    )

    counts = np.random.default_rng(5).integers(1, 300, 2000)
    for workers in (1, 2, 8, 40):
        bounds = list(chunk_bounds(counts, workers))
        assert bounds[0][0] == 0 and bounds[-1][1] == len(counts)
        assert all(b[1] == c[0] and b[0] < b[1] for b, c in itertools.pairwise(bounds))
        left = int(counts.sum())
        for lo, hi in bounds:
            share = 2 * max(workers, GUIDED_WORKERS)
            size = min(PATHS_PER_CHUNK, max(MIN_PATHS_PER_CHUNK, left // share))
            paths = int(counts[lo:hi].sum())
            assert paths >= size or hi == len(counts)
            assert paths - counts[hi - 1] < size  # the texel that reached it is the last
            left -= paths
    assert list(chunk_bounds(np.zeros(0, np.int64), 2)) == []


def test_cosine_directions_match_numpy_reference(normals):
    keys = rng.path_keys(3, np.arange(len(normals)), np.zeros(len(normals), np.int64))
    got = kernels.cosine_directions(keys, 4, np.ascontiguousarray(normals.T)).T
    local = sample_cosine_hemisphere(rng.uniform2(keys, 4))
    expected = to_world(local, normals.astype(np.float64))
    # single-precision trigonometry of an angle up to 2π: a few ulps of 2π
    np.testing.assert_allclose(got, expected, atol=5e-6)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=5e-6)


def test_cosine_directions_do_not_depend_on_the_split(normals):
    """The loop runs in SIMD lanes with a scalar remainder: both must give the same bits,
    or a bake would depend on how its paths were cut into chunks (its worker count)."""
    keys = rng.path_keys(9, np.arange(len(normals)), np.zeros(len(normals), np.int64))
    rows = np.ascontiguousarray(normals.T)
    whole = kernels.cosine_directions(keys, 2, rows)
    parts = [kernels.cosine_directions(keys[i:i + 37], 2, np.ascontiguousarray(rows[:, i:i + 37]))
             for i in range(0, len(keys), 37)]
    np.testing.assert_array_equal(whole, np.concatenate(parts, axis=1))


def test_cosine_directions_are_cosine_distributed(normals):
    """E[cos θ] = 2/3 and E[cos² θ] = 1/2 under p = cos θ/π; tolerance 5 standard errors
    (Var cos θ = 1/2 − 4/9 = 1/18)."""
    n = np.repeat(normals[:1], 200000, axis=0)
    keys = rng.path_keys(0, np.arange(len(n)), np.zeros(len(n), np.int64))
    cos = kernels.cosine_directions(keys, 0, np.ascontiguousarray(n.T)).T.astype(
        np.float64) @ n[0]
    assert cos.min() >= -1e-6
    se = np.sqrt(1 / 18 / len(cos))
    assert abs(cos.mean() - 2 / 3) < 5 * se
    assert abs((cos**2).mean() - 1 / 2) < 5 * np.sqrt(np.var(cos**2) / len(cos))


def _elementary_cells(first, second, m, a):
    """(N,) index of the elementary box of shape 2⁻ᵃ × 2⁻⁽ᵐ⁻ᵃ⁾ holding each point of two
    (N,) uint32 words."""
    x = first.astype(np.uint64) >> np.uint64(32 - a) if a else np.zeros(len(first), np.uint64)
    y = second.astype(np.uint64) >> np.uint64(32 - (m - a)) if m - a else 0
    return x * np.uint64(2 ** (m - a)) + y


@pytest.mark.parametrize("shift", [(0, 0), (0x9E3779B9, 0x12345678)])
def test_net_words_are_a_0_2_sequence(shift):
    """Every aligned run of 2ᵐ points (m ≤ 8) puts one point in each elementary box of
    every shape, with and without a digital shift; the first words are the van der
    Corput sequence."""
    words = np.array([sampling_kernels.net_words(i) for i in range(1024)], np.uint32)
    assert [int(w) for w in words[:4, 0]] == [0, 1 << 31, 1 << 30, 3 << 30]
    first, second = words[:, 0] ^ np.uint32(shift[0]), words[:, 1] ^ np.uint32(shift[1])
    for m in range(1, 9):
        for start in range(0, 1024, 2 ** m):
            run = slice(start, start + 2 ** m)
            for a in range(m + 1):
                cells = _elementary_cells(first[run], second[run], m, a)
                assert len(np.unique(cells)) == 2 ** m, (m, start, a)


def _stratified(seed, texels, samples, normals, upper=0):
    """`kernels.stratify_first_directions` of paths (texel ids, ranks on a level: sample
    indices on a view's one level) about (N, 3) unit `normals`, on their texels' upper
    level where `upper`: (N, 3) float64 directions."""
    pos = np.arange(len(texels))
    dirs = np.zeros((3, len(texels)), np.float32)
    strata = 2 * np.asarray(samples, np.int64) + upper
    kernels.stratify_first_directions(np.uint32(rng.seed_key(seed)), np.asarray(texels),
                                      pos, strata, np.ascontiguousarray(normals.T), dirs)
    return dirs.T.astype(np.float64)


@pytest.mark.parametrize("upper", [0, 1])
def test_stratified_directions_are_cosine_distributed_and_stratified(normals, upper):
    """Over many texels each sample is cosine-distributed about the normal (E[cos θ] = 2/3
    and E[cos² θ] = 1/2 within 5 standard errors); within a texel, its 16 samples on a
    level (its lower, or its upper) fall one in each of 16 cells of equal cosine-weighted
    solid angle (4 rings of equal cos²θ share × 4 quarters of azimuth: the net's 4 × 4
    boxes), where 16 independent samples fill 11 on average."""
    texels = np.repeat(np.arange(20000), 16)
    samples = np.tile(np.arange(16), 20000)
    up = np.zeros((len(texels), 3), np.float32)
    up[:, 2] = 1
    dirs = _stratified(7, texels, samples, up, upper)
    cos = dirs[:, 2]
    assert cos.min() >= -1e-6
    assert abs(cos.mean() - 2 / 3) < 5 * np.sqrt(1 / 18 / len(cos))
    assert abs((cos**2).mean() - 1 / 2) < 5 * np.sqrt(np.var(cos**2) / len(cos))
    ring = np.minimum((4 * (1 - cos**2)).astype(int), 3)  # u0 = sin²θ = 1 − cos²θ
    turn = np.arctan2(dirs[:, 1], dirs[:, 0]) / (2 * np.pi) % 1
    cells = (4 * ring + np.minimum((4 * turn).astype(int), 3)).reshape(-1, 16)
    # the frame's tangent is fixed for one normal, so the net's boxes are these cells,
    # up to rounding at their edges
    filled = np.array([len(np.unique(c)) for c in cells])
    assert np.mean(filled == 16) > 0.99
    keys = rng.path_keys(7, texels, samples)
    plain = kernels.cosine_directions(keys, 0, np.ascontiguousarray(up.T)).T.astype(np.float64)
    ring_p = np.minimum((4 * (1 - plain[:, 2] ** 2)).astype(int), 3)
    turn_p = np.arctan2(plain[:, 1], plain[:, 0]) / (2 * np.pi) % 1
    cells_p = (4 * ring_p + np.minimum((4 * turn_p).astype(int), 3)).reshape(-1, 16)
    assert np.mean([len(np.unique(c)) for c in cells_p]) < 11.5


def test_stratified_directions_depend_on_texel_and_sample_only(normals):
    """The same bits whatever order or chunk the paths come in (a view's picture is the
    same for any number of threads), and other texels, and a texel's other level, take
    other shifts."""
    texels = np.repeat(np.arange(50), 8)
    samples = np.tile(np.arange(8), 50)
    n = np.repeat(normals[:50], 8, axis=0)
    whole = _stratified(3, texels, samples, n)
    order = np.random.default_rng(0).permutation(len(texels))
    np.testing.assert_array_equal(_stratified(3, texels[order], samples[order], n[order]),
                                  whole[order])
    assert not np.array_equal(whole[:8], _stratified(3, texels[8:16], samples[:8], n[:8]))
    upper = _stratified(3, texels, samples, n, 1)
    assert not np.isclose(upper, whole).all(axis=1).any()


def _next_vertices_numpy(pos, dirs, t, ng, prim, beta, albedo, offset):
    hit = prim >= 0
    d = dirs[hit]
    g = ng[hit]
    flip = np.where((g * d).sum(axis=1, keepdims=True) > 0, -1.0, 1.0)
    g = g * (flip / np.linalg.norm(g, axis=1, keepdims=True))
    p = pos[hit] + t[hit, None] * d + offset * g
    return np.flatnonzero(hit), p, g, beta[hit] * albedo


def test_next_vertices_match_numpy_reference():
    r = np.random.default_rng(5)
    m = 1000
    pos, dirs, ng = (r.normal(size=(m, 3)).astype(np.float32) for _ in range(3))
    t = r.uniform(0.1, 5, m).astype(np.float32)
    prim = np.where(r.uniform(size=m) < 0.6, r.integers(0, 99, m), -1).astype(np.int32)
    beta = r.uniform(size=(m, 3)).astype(np.float32)
    albedo = np.array([0.2, 0.5, 0.9], np.float32)
    keys = rng.path_keys(1, np.arange(m), np.zeros(m, np.int64))
    alive = np.sort(r.choice(3 * m, m, replace=False))
    result = r.random((3 * m, 3))
    want_result = result.copy()
    radiance = np.array([1.0, 2.0, 3.0])
    escaped = prim < 0
    want_result[alive[escaped]] += beta[escaped] * radiance
    new_pos, new_n, new_beta, new_dirs, new_keys, new_alive = kernels.next_vertices(
        *(np.ascontiguousarray(a.T) for a in (pos, dirs)), t, ng, prim,
        np.ascontiguousarray(beta.T), keys, alive, albedo, 1e-3, result, radiance, 8)
    rows, p, g, b = _next_vertices_numpy(pos, dirs, t, ng, prim, beta, albedo, 1e-3)
    np.testing.assert_array_equal(new_alive, alive[rows])
    np.testing.assert_array_equal(new_keys, keys[rows])
    for a, want in ((new_pos, p), (new_n, g), (new_beta, b)):
        np.testing.assert_allclose(a.T, want, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(result, want_result, rtol=1e-15)
    np.testing.assert_array_equal(new_dirs, kernels.cosine_directions(new_keys, 8, new_n))
    facing = (new_n.T * dirs[rows]).sum(axis=1)
    assert np.all(facing <= 0)  # turned towards the arriving ray


def test_add_escaped_adds_only_escaped_rays():
    result = np.zeros((4, 3))
    alive = np.array([3, 1, 0], np.int64)
    prim = np.array([-1, 5, -1], np.int32)
    beta = np.array([[1, 2, 3], [4, 5, 6], [0.5, 0.5, 0.5]], np.float32)
    kernels.add_escaped(result, alive, prim, np.ascontiguousarray(beta.T),
                        np.array([1.0, 10.0, 100.0]))
    np.testing.assert_allclose(result, [[0.5, 5, 50], [0, 0, 0], [0, 0, 0], [1, 20, 300]])
    kernels.add_escaped(result, alive, prim, np.ascontiguousarray(beta.T), np.zeros(3))
    np.testing.assert_allclose(result, [[0.5, 5, 50], [0, 0, 0], [0, 0, 0], [1, 20, 300]])


def test_accumulate_adds_texel_sums_like_reduceat():
    r = np.random.default_rng(2)
    pos = np.sort(r.integers(0, 50, 3000))
    est = r.uniform(size=(3000, 3))
    weights = np.zeros(3)
    weights[:3] = LUMINANCE
    acc_sum, acc_second, acc_n = r.random((60, 3)), r.random(60), r.integers(0, 5, 60)
    want = acc_sum.copy(), acc_second.copy(), acc_n.copy()
    kernels.accumulate(pos, est, weights, acc_sum, acc_second, acc_n)
    starts = np.flatnonzero(np.r_[True, pos[1:] != pos[:-1]])
    texels = pos[starts]
    want[0][texels] += np.add.reduceat(est, starts, axis=0)
    want[1][texels] += np.add.reduceat((est @ LUMINANCE) ** 2, starts)
    want[2][texels] += np.diff(np.r_[starts, len(pos)])
    np.testing.assert_allclose(acc_sum, want[0], rtol=1e-12)
    np.testing.assert_allclose(acc_second, want[1], rtol=1e-12)
    np.testing.assert_array_equal(acc_n, want[2])


SKIES = ["sky:sun=3", "sky:sun=5,sun_el=10,sun_radius=2,horizon_blur=0", "sky"]


def test_sincos_turns_matches_libm():
    """|error| ≤ 3e-7: float32 rounding of the result (the series are exact to 3e-8)."""
    u = np.random.default_rng(3).random(20000).astype(np.float32)
    u = np.concatenate([u, np.float32([0, 0.125, 0.25, 0.5, 0.75, 1 - 2**-24])])
    got = np.array([sampling_kernels.sincos_turns(x) for x in u])
    angle = 2 * np.pi * u.astype(np.float64)
    np.testing.assert_allclose(got[:, 0], np.cos(angle), atol=3e-7)
    np.testing.assert_allclose(got[:, 1], np.sin(angle), atol=3e-7)


def test_commit_means_matches_numpy_running_means():
    """Bit for bit the float64 expression the numpy commit used; merged sums cleared,
    texels with no pass sample untouched."""
    gen = np.random.default_rng(5)
    values = gen.random((50, 3)).astype(np.float32)
    samples = gen.integers(0, 4, 50).astype(np.uint32)
    second = gen.random(50).astype(np.float32)
    ids = np.sort(gen.choice(50, 20, replace=False)).astype(np.int64)
    acc_sum, acc_second = gen.random((20, 3)), gen.random(20)
    acc_n = gen.integers(0, 3, 20).astype(np.int64)
    acc_sum[acc_n == 0], acc_second[acc_n == 0] = 0, 0  # no sample, no sum
    positions = np.arange(0, 20, 2)
    merged = positions[acc_n[positions] > 0]
    flat = ids[merged]
    old = samples[flat].astype(np.float64)
    new = old + acc_n[merged]
    want_values = values.copy()
    want_values[flat] = (values[flat] * old[:, None] + acc_sum[merged]) / new[:, None]
    want_second = second.copy()
    want_second[flat] = (second[flat] * old + acc_second[merged]) / new
    want_samples = samples.copy()
    want_samples[flat] = new.astype(np.uint32)
    fresh = kernels.commit_means(ids, positions, values, samples, second, acc_sum,
                                 acc_second, acc_n)
    assert fresh == int(np.count_nonzero(old == 0))
    np.testing.assert_array_equal(values, want_values)
    np.testing.assert_array_equal(second, want_second)
    np.testing.assert_array_equal(samples, want_samples)
    assert not acc_n[positions].any() and not acc_sum[positions].any()
    assert acc_n[1::2].any()  # the others are kept



def test_shadow_rays_and_unblocked_sums_match_numpy():
    gen = np.random.default_rng(9)
    m = 200
    useful = gen.random(m) < 0.6
    pos = gen.random((m, 3)).astype(np.float32)
    dirs = gen.random((m, 3)).astype(np.float32)
    idx, origins, out = sky_kernels.shadow_rays(useful, np.ascontiguousarray(pos.T),
                                                np.ascontiguousarray(dirs.T))
    np.testing.assert_array_equal(idx, np.flatnonzero(useful))
    np.testing.assert_array_equal(origins.T, pos[idx])
    np.testing.assert_array_equal(out.T, dirs[idx])
    alive = np.sort(gen.choice(500, m, replace=False))
    beta, contrib = gen.random((m, 3)).astype(np.float32), gen.random((m, 3))
    blocked = gen.random(len(idx)) < 0.3
    result = gen.random((500, 3))
    want = result.copy()
    kept = idx[~blocked]
    want[alive[kept]] += beta[kept] * contrib[kept]
    sky_kernels.add_unblocked(result, alive, idx, blocked, np.ascontiguousarray(beta.T),
                              np.ascontiguousarray(contrib.T))
    np.testing.assert_allclose(result, want, rtol=1e-15)


@pytest.mark.parametrize("spec", SKIES)
def test_sky_light_samples_match_the_environment(spec, normals):
    """The compiled sky sampler against `SkyEnvironment.sample/pdf/radiance` and the
    MIS weighting of `integrator._direct_env`, on the same uniforms."""
    from isolume.baking.environment import parse_env
    from isolume.baking.sampling import power_heuristic

    env = parse_env(spec)
    assert len(sky_kernels.sky_params(env)) == sky_kernels.SKY_PARAMS
    keys = rng.path_keys(5, np.arange(len(normals)), np.zeros(len(normals), np.int64))
    dirs, contrib, useful = sky_kernels.sky_light_samples(sky_kernels.sky_params(env), keys,
                                                          2, np.ascontiguousarray(normals.T))
    dirs, contrib = dirs.T, contrib.T
    d, pdf = env.sample(rng.uniform2(keys, 2))
    # the angle's sine and cosine in single precision (`sincos_turns`): within 3e-7
    np.testing.assert_allclose(dirs, d, atol=1e-6)
    # contributions: the environment's own formulas at the kernel's directions, away
    # from where a rounding of the direction decides (cos = 0, the sun disk's rim)
    d = dirs.astype(np.float64)
    pdf = env.pdf(d)
    cos = (normals * d).sum(axis=1)
    clear = (np.abs(cos) > 1e-6) & (np.abs(d @ env.sun_direction - env.sun_cos_radius) > 1e-6)
    assert clear.mean() > 0.98
    np.testing.assert_array_equal(useful[clear], ((cos > 0) & (pdf > 0))[clear])
    ok = useful & clear
    w = power_heuristic(pdf[ok], cos[ok] / np.pi)
    want = env.radiance(d[ok]) * (cos[ok] * w / pdf[ok])[:, None]
    np.testing.assert_allclose(contrib[ok], want, rtol=1e-5, atol=1e-6)
    assert (contrib[~useful] == 0).all()
    if env.sun_probability > 0:  # the sun cone is sampled, and weighted as such
        in_sun = d @ env.sun_direction >= env.sun_cos_radius
        assert 0.05 < in_sun.mean() < 0.95


@pytest.mark.parametrize("mis", [True, False])
@pytest.mark.parametrize("spec", SKIES)
def test_sky_escaped_rays_match_the_environment(spec, mis, normals):
    """Escaped rays' sky light, weighted against the light sample (mis) or alone."""
    from isolume.baking.environment import parse_env
    from isolume.baking.integrator import PathSettings, _add_escaped

    env = parse_env(spec)
    r = np.random.default_rng(8)
    m = len(normals)
    dirs = r.normal(size=(m, 3))
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    dirs[:50] = env.sun_direction  # some straight into the sun
    prim = np.where(r.uniform(size=m) < 0.5, -1, 3).astype(np.int32)
    beta = r.uniform(size=(m, 3)).astype(np.float32)
    alive = r.permutation(m)
    got, want = np.zeros((m, 3)), np.zeros((m, 3))
    sky_kernels.sky_add_escaped(sky_kernels.sky_params(env), got, alive, prim,
                                *(np.ascontiguousarray(a.T) for a in (beta, dirs, normals)),
                                mis)
    _add_escaped(want, alive, prim < 0, beta, dirs, normals, env, mis,
                 PathSettings(bounces=0, albedo=(1, 1, 1), hit_offset=0.0))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)


def test_rows_added_in_one_call_are_numpys_additions():
    """`kernels.add_rows` (a chunk's sums added to its batch's, `PassSums.add`) against
    numpy's ``acc[positions] += part`` for distinct positions: the same float64 sums and
    counts to the bit; the rows not named keep theirs."""
    from isolume.baking.passes import PassSums

    rng = np.random.default_rng(9)
    acc = PassSums.of(rng.random((500, 4)), rng.random(500), rng.integers(0, 9, 500))
    part = PassSums.of(rng.random((120, 4)) * 1e-7, rng.random(120), rng.integers(1, 5, 120))
    positions = rng.choice(500, 120, replace=False).astype(np.int32)
    want = PassSums.of(acc.sum.copy(), acc.second.copy(), acc.n.copy())
    want.sum[positions] += part.sum
    want.second[positions] += part.second
    want.n[positions] += part.n
    acc.add(positions, part)
    for got, expected in ((acc.sum, want.sum), (acc.second, want.second), (acc.n, want.n)):
        np.testing.assert_array_equal(got, expected)
