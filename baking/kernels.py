"""Compiled loops between Embree calls: ray generation, hit processing, accumulation.

The path tracer spends its time in two places: inside Embree, and in the per-ray
arithmetic between Embree calls (random numbers, cosine-sampled directions, the next path
vertex). Written as numpy expressions the second part costs about as much as Embree
itself, makes a dozen temporaries per ray and holds the GIL often enough that worker
threads queue for it. These numba kernels do it in one pass per stage without the GIL
(``nogil=True``), so worker threads overlap fully with each other and with Embree.

Per-ray vectors are held one row per axis, (3, N) float32: the loops then run eight
lanes wide, and Embree reads the transposed view, an (N, 3) array with strides, as it is.

`trace_chunk` strings the kernels together for a whole chunk of paths and calls Embree
itself, per ray (`embree_kernels.intersect_rays`, `embree_kernels.occluded_rays`, through
the addresses in `trace.EmbreeCalls`): no Python, and so no wait for the GIL, between a
chunk's rays. The random numbers come from `baking.sampling_kernels`, the procedural
sky's light samples and radiance from `baking.sky_kernels`.

They mirror, and are tested against, the numpy reference functions: `cosine_directions`
against `baking.sampling.sample_cosine_hemisphere` + `to_world`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from isolume.baking.embree_kernels import intersect_rays, occluded_rays
from isolume.baking.sampling_kernels import (
    GOLDEN,
    dimension_key,
    net_words,
    pcg_hash,
    sincos_turns,
    tangent_frame,
    uniform_f32,
    word_uniform_f32,
)
from isolume.baking.sky_kernels import (
    SKY_PARAMS,
    add_unblocked,
    shadow_rays,
    sky_add_escaped,
    sky_light_samples,
)
from isolume.baking.sky_kernels import sky_params as sky_params  # for `baking.bake`
from isolume.volumes.field import JIT

DIMS_PER_VERTEX = 4  # 2 for the cosine-sampled direction, 2 for the light sample
UPPER_KEY = np.uint32(0x0B0E_5EED)
"""Hashed into a texel's key for the shifts of its stratified first directions on its
upper level (`stratify_first_directions`): its two levels' paths, of their own ranks,
take independent shifts of the sequence."""


@numba.njit(**JIT)
def path_starts(seed_key: np.uint32, ids: np.ndarray, pos: np.ndarray, samples: np.ndarray,
                texels: np.ndarray, origins: np.ndarray, normals: np.ndarray):
    """Keys, origins, normals and first directions of P paths (texel positions `pos`,
    sorted, and sample indices), from the per-texel start points of one level.

    Args:
        seed_key: ``pcg_hash(seed)``; ids: (T_all,) flat lattice index of each position.
        texels: (T,) sorted positions that `origins`, `normals` (T, 3) belong to; every
            value of `pos` is among them.

    Returns:
        keys (P,) uint32 (`baking.rng.path_keys`), origins (3, P) and normals (3, P)
        float32, one row per axis (the layout `trace_paths` works in), and the paths'
        first directions (3, P): `cosine_directions` (keys, 0, normals).
    """
    count = len(pos)
    keys = np.empty(count, np.uint32)
    out_o = np.empty((3, count), np.float32)
    out_n = np.empty((3, count), np.float32)
    dirs = np.empty((3, count), np.float32)
    i = 0
    j = np.searchsorted(texels, pos[0]) if count else 0  # a chunk's texels may start late
    while i < count:  # one texel's paths at a time: the inner loop vectorises
        while texels[j] < pos[i]:  # both sorted: one merge pass
            j += 1
        end = i + 1
        while end < count and pos[end] == pos[i]:
            end += 1
        h = pcg_hash(np.uint32(np.uint32(ids[pos[i]]) ^ seed_key))
        for k in range(i, end):
            keys[k] = pcg_hash(np.uint32(h + np.uint32(samples[k]) * GOLDEN))
        for c in range(3):
            out_o[c, i:end] = origins[j, c]
            out_n[c, i:end] = normals[j, c]
        i = end
    _fill_cosine_directions(keys, 0, out_n, dirs)
    return keys, out_o, out_n, dirs


PHASE_UNIT = 2.0 ** -32
"""A plan's level-assignment phase per unit of its uint32 (`baking.plan.Plan.phase`)."""


@numba.njit(**JIT)
def on_upper(phase: np.uint32, weight: float, sample: int, golden: float) -> bool:
    """`baking.plan.Plan.on_upper` of one sample (the same float64 operations)."""
    return (phase * PHASE_UNIT + sample * golden) % 1.0 < weight


@numba.njit(**JIT)
def level_texels(here: np.ndarray, below: np.ndarray, done: np.ndarray,
                 remaining: np.ndarray, phase: np.ndarray, weight: np.ndarray,
                 golden: float):
    """The texels with pending paths on one isovalue level, sorted, and how many each has.

    Args:
        here: (A,) sorted plan positions of texels whose lower level is this one (their
            samples on the lower level come here); below: (B,) sorted positions of texels
            whose lower level is the one below (their samples on the upper level).
        done, remaining: (T_all,) samples a texel has, and how many more it needs: its
            pending samples are ``done … done + remaining - 1``.
        phase, weight: the plan's (T_all,) level-assignment phases (uint32 in units of
            2⁻³², `Plan.phase`) and upper weights.

    Returns:
        (K,) int64 sorted positions of the texels with at least one path here, (K,) bool
        whether this is their upper level, (K,) int64 their paths here.
    """
    texels = np.empty(len(here) + len(below), np.int64)
    upper = np.empty(len(texels), np.bool_)
    counts = np.empty(len(texels), np.int64)
    k, a, b = 0, 0, 0
    while a < len(here) or b < len(below):  # merge the two sorted lists
        up = a == len(here) or (b < len(below) and below[b] < here[a])
        if up:
            p = below[b]
            b += 1
        else:
            p = here[a]
            a += 1
        count = 0
        for s in range(done[p], done[p] + remaining[p]):
            if on_upper(phase[p], weight[p], s, golden) == up:
                count += 1
        if count > 0:
            texels[k], upper[k], counts[k] = p, up, count
            k += 1
    return texels[:k], upper[:k], counts[:k]


@numba.njit(**JIT)
def texel_paths(texels: np.ndarray, upper: np.ndarray, counts: np.ndarray,
                done: np.ndarray, remaining: np.ndarray, phase: np.ndarray,
                weight: np.ndarray, golden: float):
    """The paths of (K,) texels on one level (as `level_texels` lists them: sorted
    positions, whether the level is their upper one, their path counts), samples
    ascending; `done`, `remaining`, `phase`, `weight` as there.

    Returns:
        (P,) int64 texel of each path (0 … K − 1: an index into `texels`), (P,) int64
        sample indices, P = counts.sum(), and (P,) int64 their strata: 2 r + u, r the
        sample's rank among its texel's samples on this level (all of them, those done
        before included), u 1 on the texel's upper level (`stratify_first_directions`).
    """
    total = 0
    for c in counts:
        total += c
    pos = np.empty(total, np.int64)
    samples = np.empty(total, np.int64)
    strata = np.empty(total, np.int64)
    i = 0
    for k in range(len(texels)):
        p = texels[k]
        side = 1 if upper[k] else 0
        rank = 0
        for s in range(done[p]):
            rank += on_upper(phase[p], weight[p], s, golden) == upper[k]
        for s in range(done[p], done[p] + remaining[p]):
            if on_upper(phase[p], weight[p], s, golden) == upper[k]:
                pos[i] = k
                samples[i] = s
                strata[i] = 2 * rank + side
                rank += 1
                i += 1
    return pos, samples, strata


@numba.njit(**JIT)
def cosine_directions(keys: np.ndarray, dim: int, normals: np.ndarray) -> np.ndarray:
    """(3, N) float32 world directions, cosine-distributed about the (3, N) float32 unit
    normals, from the float32 uniforms of dimensions `dim`, `dim + 1` of the (N,) uint32
    keys.

    Malley's method (a uniform disk point lifted to the hemisphere) in the frame of Duff
    et al. 2017, like `sampling.sample_cosine_hemisphere` followed by `sampling.to_world`,
    in single precision (Embree is float32 too), the angle's sine and cosine from
    `sincos_turns`. One row per axis, so that the loop runs eight lanes wide: three times
    faster than with (N, 3) rows.
    """
    out = np.empty((3, len(keys)), np.float32)
    _fill_cosine_directions(keys, dim, normals, out)
    return out


@numba.njit(**JIT)
def _fill_cosine_directions(keys: np.ndarray, dim: int, normals: np.ndarray,
                            out: np.ndarray) -> None:
    """out[:] = `cosine_directions` (keys, dim, normals)."""
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    for i in range(len(keys)):
        lx, ly, lz = _cosine_local(keys[i], k0, k1)
        nx, ny, nz = normals[0, i], normals[1, i], normals[2, i]
        tx, ty, tz, bx, by, bz = tangent_frame(nx, ny, nz)
        out[0, i] = lx * tx + ly * bx + lz * nx
        out[1, i] = lx * ty + ly * by + lz * ny
        out[2, i] = lx * tz + ly * bz + lz * nz


@numba.njit(**JIT)
def _cosine_local(key: np.uint32, k0: np.uint32, k1: np.uint32):
    """The cosine-distributed direction of a key (dimension keys k0, k1) in the frame
    whose z axis is the normal (Malley's method), float32."""
    return _cosine_of(uniform_f32(key, k0), uniform_f32(key, k1))


@numba.njit(**JIT)
def _cosine_of(u0: np.float32, u1: np.float32):
    """The cosine-distributed direction of two float32 uniforms in the frame whose z axis
    is the normal (Malley's method: radius √u0, angle u1 turns)."""
    r = np.sqrt(u0)
    c, si = sincos_turns(u1)
    return r * c, r * si, np.sqrt(np.float32(1.0) - u0)


@numba.njit(**JIT)
def stratify_first_directions(seed_key: np.uint32, ids: np.ndarray, pos: np.ndarray,
                              strata: np.ndarray, normals: np.ndarray, dirs: np.ndarray
                              ) -> None:
    """Overwrite the (3, P) first directions `dirs` of `path_starts`' P paths with
    stratified ones: a path of stratum 2 r + u (`strata` (P,): r its rank among its
    texel's paths on one level, u 1 on the texel's upper level, else 0; a view's texels
    have one level, and r its sample index) takes point r of the (0, 2)-sequence
    (`net_words`), digitally shifted by two words hashed from the texel's key (its
    `path_starts` hash, hashed once more with `UPPER_KEY` on the upper level, with
    `dimension_key` 0 and 1), as its two uniforms. Each
    direction alone is cosine-distributed as one drawn from the keys (the shift makes
    each point uniform), while a texel's first 2ᵐ samples leave through each of its
    hemisphere's 2ᵐ cells of equal cosine-weighted solid angle (the net's boxes, of
    every shape) once: the visibility of the sky, a step over the hemisphere, is
    estimated with about half the RMS error of independent samples at 32 paths
    (docs/accuracy.md). The other dimensions keep the paths' keys."""
    k0, k1 = dimension_key(0), dimension_key(1)
    shift0 = shift1 = np.uint32(0)
    for i in range(len(pos)):
        # a texel's paths on a level come together: its shifts once
        if i == 0 or pos[i] != pos[i - 1] or (strata[i] ^ strata[i - 1]) & 1:
            h = pcg_hash(np.uint32(np.uint32(ids[pos[i]]) ^ seed_key))
            if strata[i] & 1:
                h = pcg_hash(np.uint32(h ^ UPPER_KEY))
            shift0, shift1 = pcg_hash(np.uint32(h ^ k0)), pcg_hash(np.uint32(h ^ k1))
        first, second = net_words(strata[i] >> 1)
        u0 = word_uniform_f32(np.uint32(first ^ shift0))
        u1 = word_uniform_f32(np.uint32(second ^ shift1))
        lx, ly, lz = _cosine_of(u0, u1)
        nx, ny, nz = normals[0, i], normals[1, i], normals[2, i]
        tx, ty, tz, bx, by, bz = tangent_frame(nx, ny, nz)
        dirs[0, i] = lx * tx + ly * bx + lz * nx
        dirs[1, i] = lx * ty + ly * by + lz * ny
        dirs[2, i] = lx * tz + ly * bz + lz * nz


@numba.njit(**JIT)
def next_vertices(pos: np.ndarray, dirs: np.ndarray, t: np.ndarray, ng: np.ndarray,
                  prim: np.ndarray, beta: np.ndarray, keys: np.ndarray, alive: np.ndarray,
                  albedo: np.ndarray, offset: float, result: np.ndarray,
                  escaped_radiance: np.ndarray, dim: int):
    """Where the M rays of one path vertex lead: escaped rays bring a constant
    environment's light home, hits become the next vertices, with their cosine-sampled
    directions.

    Each hit point p = pos + t·dir (float32, like Embree's own) is pushed `offset` (world
    units) off the facet along its geometric normal, turned towards the arriving ray
    (bounce vertices use the facet normal: a smoothed normal would send some directions
    into the facet at grazing angles, where rays starting this close to it can slip
    between triangles). Throughputs are multiplied by the (3,) albedo.

    Args:
        pos, dirs, beta: (3, M) float32 ray origins, directions and path throughputs.
        t: (M,) hit distances, ng: (M, 3) unnormalised facet normals, prim: (M,)
            triangle ids (< 0: escaped) — Embree's answers.
        keys: (M,) uint32 path keys; alive: (M,) int64 rows of `result` the rays add to.
        result, escaped_radiance: as `add_escaped` (done here for the escaped rays).
        dim: the first random dimension of the new vertices' directions.

    Returns:
        positions, unit normals, throughputs and `cosine_directions` (3, H) float32, keys
        (H,) uint32 and result rows (H,) int64 of the H rays that hit.
    """
    add_escaped(result, alive, prim, beta, escaped_radiance)
    rows = np.empty(len(prim) + 1, np.int64)  # the rays that hit, listed without branches
    hits = 0  # (a branch on a random hit or miss mispredicts half the time)
    for i in range(len(prim)):
        rows[hits] = i
        hits += prim[i] >= 0
    new_pos = np.empty((3, hits), np.float32)
    new_n = np.empty((3, hits), np.float32)
    new_beta = np.empty((3, hits), np.float32)
    new_keys = np.empty(hits, np.uint32)
    new_alive = np.empty(hits, np.int64)
    for j in range(hits):
        i = rows[j]
        gx, gy, gz = ng[i, 0], ng[i, 1], ng[i, 2]
        facing = gx * dirs[0, i] + gy * dirs[1, i] + gz * dirs[2, i]
        scale = np.float32(-1.0 if facing > 0 else 1.0) / max(
            np.float32(math.sqrt(gx * gx + gy * gy + gz * gz)), np.float32(1e-30))
        for c in range(3):
            normal = ng[i, c] * scale
            new_n[c, j] = normal
            new_pos[c, j] = (pos[c, i] + t[i] * dirs[c, i]) + np.float32(offset) * normal
            new_beta[c, j] = beta[c, i] * albedo[c]
        new_keys[j] = keys[i]
        new_alive[j] = alive[i]
    new_dirs = np.empty((3, hits), np.float32)
    _fill_cosine_directions(new_keys, dim, new_n, new_dirs)
    return new_pos, new_n, new_beta, new_dirs, new_keys, new_alive


@numba.njit(**JIT)
def add_escaped(result: np.ndarray, alive: np.ndarray, prim: np.ndarray,
                beta: np.ndarray, radiance: np.ndarray) -> None:
    """result[alive[i], :3] += beta[:, i] · radiance for every ray i that escaped
    (``prim < 0``): a constant environment seen by a cosine-sampled ray, where
    `radiance` (3,) is π·L (nothing to do when it is zero); beta (3, M)."""
    if radiance[0] == 0 and radiance[1] == 0 and radiance[2] == 0:
        return
    for i in range(len(prim)):  # without branches: rays that hit add exactly 0
        escaped = np.float64(prim[i] < 0)
        row = alive[i]
        for c in range(3):
            result[row, c] += beta[c, i] * radiance[c] * escaped


@numba.njit(**JIT)
def add_rows(positions: np.ndarray, acc_sum: np.ndarray, acc_second: np.ndarray,
             acc_n: np.ndarray, add_sum: np.ndarray, add_second: np.ndarray,
             add_n: np.ndarray) -> None:
    """acc_*[positions[r]] += add_*[r] for the (N,) distinct `positions` (sums (A, C) and
    (N, C), seconds and path counts (A,) and (N,)): the pass sums of some texels added to
    a batch's (`passes.PassSums.add`)."""
    for r in range(len(positions)):
        p = positions[r]
        for c in range(acc_sum.shape[1]):
            acc_sum[p, c] += add_sum[r, c]
        acc_second[p] += add_second[r]
        acc_n[p] += add_n[r]


@numba.njit(**JIT)
def accumulate(pos: np.ndarray, estimates: np.ndarray, weights: np.ndarray,
               acc_sum: np.ndarray, acc_second: np.ndarray, acc_n: np.ndarray) -> None:
    """Add path estimates to the pass sums of their texels: each texel's paths are summed
    in order first, then added to its sums (the same arithmetic whatever the chunking).

    Args:
        pos: (P,) texel positions (plan indices), sorted (equal positions adjacent).
        estimates: (P, C) per-path estimates.
        weights: (C,) luminance weights for the second moment (zeros but the first
            for SH transfer).
        acc_sum: (A, C), acc_second: (A,) Σ lum², acc_n: (A,) paths — the pass sums,
            updated in place (chunks running at once hold disjoint texels).
    """
    channels = estimates.shape[1]
    local = np.zeros(channels)
    i = 0
    while i < len(pos):
        p = pos[i]
        local[:] = 0.0
        second = 0.0
        n = 0
        while i < len(pos) and pos[i] == p:
            lum = 0.0
            for c in range(channels):
                local[c] += estimates[i, c]
                lum += weights[c] * estimates[i, c]
            second += lum * lum
            n += 1
            i += 1
        for c in range(channels):
            acc_sum[p, c] += local[c]
        acc_second[p] += second
        acc_n[p] += n


@numba.njit(**JIT)
def commit_means(ids: np.ndarray, positions: np.ndarray, values: np.ndarray,
                 samples: np.ndarray, second: np.ndarray, acc_sum: np.ndarray,
                 acc_second: np.ndarray, acc_n: np.ndarray) -> int:
    """Merge pass sums into running means, in float64 like the numpy expression
    ``(mean·old + sum) / (old + n)``, and clear the merged sums.

    Args:
        ids: (A,) flat lattice ids of the plan's texels; positions: (K,) plan positions to
            merge (those with no pass sample are skipped).
        values: (Z·Y·X, C) float32 means; samples: (Z·Y·X,) uint32 counts; second:
            (Z·Y·X,) float32 mean squared luminance — the lattice's, updated in place.
        acc_sum: (A, C), acc_second: (A,) float64 and acc_n: (A,) int64 pass sums.

    Returns:
        how many merged texels had no sample before.
    """
    fresh = 0
    for p in positions:
        n = acc_n[p]
        if n == 0:
            continue
        f = ids[p]
        old = np.float64(samples[f])
        new = old + n
        for c in range(values.shape[1]):
            values[f, c] = (values[f, c] * old + acc_sum[p, c]) / new
            acc_sum[p, c] = 0.0
        second[f] = (second[f] * old + acc_second[p]) / new
        samples[f] = np.uint32(new)
        acc_second[p] = 0.0
        acc_n[p] = 0
        fresh += old == 0
    return fresh


# -- a chunk of paths in one compiled call, Embree called per ray --------------------------
RAY_RECORD_ROWS = 7
"""Columns of a recording of traced rays: origin (3), direction (3), 1 for an occlusion
query (0: closest hit)."""


@numba.njit(**JIT)
def _record(record: np.ndarray, recorded: int, kind: float, pos: np.ndarray,
            dirs: np.ndarray) -> int:
    """Append the (3, M) rays to `record` (capacity, RAY_RECORD_ROWS) with their kind
    (1: occlusion, 0: closest hit) unless it has no rows; returns the new count."""
    if len(record) == 0:
        return recorded
    if recorded + pos.shape[1] > len(record):
        raise ValueError("ray record too small for the rays traced")
    for i in range(pos.shape[1]):
        for c in range(3):
            record[recorded + i, c] = pos[c, i]
            record[recorded + i, 3 + c] = dirs[c, i]
        record[recorded + i, 6] = kind
    return recorded + pos.shape[1]


@numba.njit(**JIT)
def trace_chunk(calls: tuple[int, ...], seed_key: np.uint32, ids: np.ndarray, pos: np.ndarray,
                samples: np.ndarray, texels: np.ndarray, origins: np.ndarray,
                normals: np.ndarray, strata: np.ndarray, bounces: int, albedo: np.ndarray,
                offset: float,
                escaped_radiance: np.ndarray, sky: np.ndarray, first_sky: np.ndarray,
                first_sampled: bool, use_sky: bool, weights: np.ndarray,
                acc_sum: np.ndarray, acc_second: np.ndarray, acc_n: np.ndarray,
                record: np.ndarray) -> int:
    """`path_starts`, `integrator.trace_paths` and `accumulate` of a chunk of paths in one
    compiled call, for irradiance under a constant environment or the procedural sky (no
    point or directional lights): the same kernels, vertex by vertex over all the paths,
    with Embree called per ray from compiled code (`intersect_rays`, `occluded_rays`)
    instead of one embreex batch per step — no Python, no GIL between a chunk's rays —
    so the pass sums are the same to the bit (tested).

    Args:
        calls: (scene handle, rtcIntersect1 address, rtcOccluded1 address).
        seed_key, ids, pos, samples, texels, origins, normals: as `path_starts` (P paths
            sorted by texel position; (T, 3) float32 start points and unit normals).
        strata: (P,) the paths' strata: first directions by `stratify_first_directions`,
            or (0,): by the keys.
        albedo: (3,) float32; offset: world distance hit points leave the surface by.
        escaped_radiance: (3,) π·L of a constant environment (zero under the sky).
        sky: (SKY_PARAMS,) `sky_params` (any values when not `use_sky`); first_sky: those
            of the sky the first vertex sees (`sky_without_sun` when the sun's direct
            light is shaded per pixel, else `sky`); first_sampled: whether the first vertex
            takes a light sample of it (else its cosine-sampled ray alone sees it).
        weights, acc_sum, acc_second, acc_n: as `accumulate` (acc_sum (A, 3)).
        record: (capacity, RAY_RECORD_ROWS) float32 for benchmarks (every ray traced is
            appended; capacity P·2·(bounces + 1) suffices), or (0, RAY_RECORD_ROWS).

    Returns:
        rays traced.
    """
    keys, at, n, dirs = path_starts(seed_key, ids, pos, samples, texels, origins, normals)
    if len(strata):
        stratify_first_directions(seed_key, ids, pos, strata, n, dirs)
    result = np.zeros((len(pos), 3))
    alive = np.arange(len(pos))
    beta = np.ones((3, len(pos)), np.float32)
    rays, recorded = 0, 0
    for vertex in range(bounces + 1):
        dim = vertex * DIMS_PER_VERTEX
        seen = first_sky if vertex == 0 else sky
        sampled = first_sampled or vertex > 0
        if use_sky and sampled:
            light, contrib, useful = sky_light_samples(seen, keys, dim + 2, n)
            idx, shadow_at, shadow_dirs = shadow_rays(useful, at, light)
            blocked = occluded_rays(calls, shadow_at, shadow_dirs)
            recorded = _record(record, recorded, 1.0, shadow_at, shadow_dirs)
            rays += len(idx)
            add_unblocked(result, alive, idx, blocked, beta, contrib)
        last = vertex == bounces
        if last:  # only whether the ray escapes matters
            prim = np.where(occluded_rays(calls, at, dirs), np.int32(0), np.int32(-1))
            t, ng = np.empty(0, np.float32), np.empty((0, 3), np.float32)
        else:
            t, prim, ng = intersect_rays(calls, at, dirs)
        recorded = _record(record, recorded, 1.0 if last else 0.0, at, dirs)
        rays += len(prim)
        if use_sky:
            sky_add_escaped(seen, result, alive, prim, beta, dirs, n, sampled)
        if last:
            add_escaped(result, alive, prim, beta, escaped_radiance)
            break
        at, n, beta, dirs, keys, alive = next_vertices(
            at, dirs, t, ng, prim, beta, keys, alive, albedo, offset, result,
            escaped_radiance, dim + DIMS_PER_VERTEX)
        if len(alive) == 0:
            break
    accumulate(pos, result, weights, acc_sum, acc_second, acc_n)
    return rays


@numba.njit(**JIT)
def neighbour_medians(ids: np.ndarray, variance: np.ndarray, nz: int, ny: int, nx: int,
                      which: np.ndarray, out: np.ndarray) -> None:
    """Into (K,) `out`: for each of the texels at positions (K,) `which` of (N,) sorted
    flat lattice `ids` of an (nz, ny, nx) box, the median of the (N,) `variance` of its
    26-connected neighbours among `ids` (0 where it has none)."""
    found = np.empty(26)
    n = len(ids)
    for k in range(len(which)):
        flat = ids[which[k]]
        z, rest = divmod(flat, ny * nx)
        y, x = divmod(rest, nx)
        count = 0
        for dz in range(-1, 2):
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    zz, yy, xx = z + dz, y + dy, x + dx
                    if ((dz == 0 and dy == 0 and dx == 0) or zz < 0 or yy < 0 or xx < 0
                            or zz >= nz or yy >= ny or xx >= nx):
                        continue
                    other = (zz * ny + yy) * nx + xx
                    at = np.searchsorted(ids, other)
                    if at < n and ids[at] == other:
                        value = variance[at]
                        slot = count  # insertion sort: `found` stays ascending
                        while slot > 0 and found[slot - 1] > value:
                            found[slot] = found[slot - 1]
                            slot -= 1
                        found[slot] = value
                        count += 1
        if count == 0:
            out[k] = 0.0
        else:
            out[k] = 0.5 * (found[(count - 1) // 2] + found[count // 2])


@numba.njit(**JIT)
def lower_corner(c: float, n: int) -> int:
    """The lower corner along one axis of a trilinear lookup at texel coordinate `c` in a
    grid `n` texels long, clamped as `lattice.trilinear_corners` clamps."""
    if c != c:  # NaN: the first texel, as numpy's clamps leave it
        return 0
    c = min(max(c, 0.0), n - 1.0)
    return max(min(math.floor(c), n - 2), 0)


def warm_up() -> None:
    """Load (or compile, the first time on a machine) every kernel for the argument types
    the path tracer uses, so that the first bake's timings measure tracing only."""
    keys = np.zeros(1, np.uint32)
    vec = np.ones((3, 1), np.float32)
    prim = np.zeros(1, np.int32)
    index = np.zeros(1, np.int64)
    result = np.zeros((1, 3))
    dirs = cosine_directions(keys, 0, vec)
    next_vertices(vec, dirs, np.ones(1, np.float32), vec.T.copy(), prim, vec, keys, index,
                  np.ones(3, np.float32), 1e-3, result, np.ones(3), 4)
    add_escaped(result, index, prim, vec, np.ones(3))
    accumulate(index, result, np.ones(3), np.zeros((1, 3)), np.zeros(1), index.copy())
    path_starts(np.uint32(0), index, index, index, index, vec.T.copy(), vec.T.copy())
    small = np.zeros(1, np.int32)  # a bake's positions, and its samples done and to do
    for count in (np.zeros(1, np.uint16), small):  # in 2 bytes where they fit
        texels, upper, counts = level_texels(small, small, count, count, np.zeros(1),
                                             np.zeros(1), 0.5)
        texel_paths(texels, upper, counts, count, count, np.zeros(1), np.zeros(1), 0.5)
    sky = np.zeros(SKY_PARAMS)
    stratify_first_directions(np.uint32(0), index, index, index, vec, vec.copy())
    trace_chunk((0, 0, 0), np.uint32(0), index, index[:0], index[:0], index, vec.T.copy(),
                vec.T.copy(), index[:0], 2, np.ones(3, np.float32), 1e-3, np.ones(3), sky, sky,
                True, True,
                np.ones(3), np.zeros((1, 3)), np.zeros(1), index.copy(),
                np.empty((0, RAY_RECORD_ROWS), np.float32))
    _, contrib, useful = sky_light_samples(sky, keys, 0, vec)
    idx, _, _ = shadow_rays(useful, vec, vec)
    add_unblocked(result, index, idx, np.zeros(len(idx), np.bool_), vec, contrib)
    sky_add_escaped(sky, result, index, prim, vec, vec, vec, True)
    neighbour_medians(index, np.zeros(1), 1, 1, 1, index, np.zeros(1))
