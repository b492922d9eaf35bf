"""Compiled loops between Embree calls: ray generation, hit processing, accumulation.

The path tracer spends its time in two places: inside Embree, and in the per-ray
arithmetic between Embree calls (random numbers, cosine-sampled directions, the next path
vertex). Written as numpy expressions the second part costs about as much as Embree
itself, makes a dozen temporaries per ray and holds the GIL often enough that worker
threads queue for it. These numba kernels do it in one pass per stage without the GIL
(``nogil=True``), so worker threads overlap fully with each other and with Embree.

Per-ray vectors are held one row per axis, (3, N) float32: the loops then run eight
lanes wide, and Embree reads the transposed view, an (N, 3) array with strides, as it is.

They mirror, and are tested against, the numpy reference functions: `pcg_hash` and
`uniform` against `baking.rng` (bit for bit), `cosine_directions` against
`baking.sampling.sample_cosine_hemisphere` + `to_world`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True, "error_model": "numpy"}

_MASK = np.uint64(0xFFFFFFFF)
_MULT = np.uint64(747796405)
_INC = np.uint64(2891336453)
_M2 = np.uint64(277803737)
_GOLDEN = np.uint64(0x9E3779B9)
_INV_2_32 = 1.0 / 4294967296.0


@numba.njit(**_JIT)
def pcg_hash(x: np.uint64) -> np.uint64:
    """PCG-RXS-M-XS hash of a 32-bit word held in a uint64 (`baking.rng.pcg_hash`)."""
    state = (x * _MULT + _INC) & _MASK
    word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state) * _M2) & _MASK
    return (word >> np.uint64(22)) ^ word


@numba.njit(**_JIT)
def dimension_key(dim: int) -> np.uint64:
    """The hash that selects random dimension `dim` (`baking.rng.uniform`)."""
    return pcg_hash((np.uint64(dim) + _GOLDEN) & _MASK)


@numba.njit(**_JIT)
def uniform(key: np.uint32, dim_key: np.uint64) -> float:
    """The uniform in [0, 1) of a path key and a dimension key (`baking.rng.uniform`)."""
    return float(pcg_hash(np.uint64(key) ^ dim_key)) * _INV_2_32


@numba.njit(**_JIT)
def uniform31(key: np.uint32, dim_key: np.uint64) -> float:
    """`uniform` from the hash's top 31 bits: through a signed 32-bit conversion, which
    vectorises (an unsigned 64-bit one does not), within 2^-32 of `uniform`."""
    return float(np.int32(pcg_hash(np.uint64(key) ^ dim_key) >> np.uint64(1))) * 2.0**-31


@numba.njit(**_JIT)
def uniform_f32(key: np.uint32, dim_key: np.uint64) -> np.float32:
    """`uniform31` in single precision, strictly below 1 (clamped to the largest float32
    below 1, where rounding would reach 1)."""
    return min(np.float32(uniform31(key, dim_key)), np.float32(1.0 - 2.0**-24))


@numba.njit(**_JIT)
def uniform2(keys: np.ndarray, dim: int) -> np.ndarray:
    """(N, 2) float64 uniforms of dimensions `dim`, `dim + 1` (`baking.rng.uniform2`)."""
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    out = np.empty((len(keys), 2))
    for i in range(len(keys)):
        out[i, 0] = uniform(keys[i], k0)
        out[i, 1] = uniform(keys[i], k1)
    return out


@numba.njit(**_JIT)
def _frame(nx, ny, nz):
    """Tangents (tx, ty, tz), (bx, by, bz) completing the unit normal n to a right-handed
    frame (Duff et al. 2017, branchless; `baking.sampling.orthonormal_basis`), in the
    precision of n (float32 normals stay float32 inside vectorised loops)."""
    one = np.float32(1.0)
    sign = one if nz >= 0 else -one
    a = -one / (sign + nz)
    b = nx * ny * a
    return one + sign * nx * nx * a, sign * b, -sign * nx, b, sign + ny * ny * a, -ny


@numba.njit(**_JIT)
def path_starts(seed_key: np.uint64, ids: np.ndarray, pos: np.ndarray, samples: np.ndarray,
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
    i, j = 0, 0
    while i < count:  # one texel's paths at a time: the inner loop vectorises
        while texels[j] < pos[i]:  # both sorted: one merge pass
            j += 1
        end = i + 1
        while end < count and pos[end] == pos[i]:
            end += 1
        h = pcg_hash(np.uint64(np.uint32(ids[pos[i]])) ^ seed_key)
        for k in range(i, end):
            keys[k] = np.uint32(pcg_hash((h + np.uint64(samples[k]) * _GOLDEN) & _MASK))
        for c in range(3):
            out_o[c, i:end] = origins[j, c]
            out_n[c, i:end] = normals[j, c]
        i = end
    _fill_cosine_directions(keys, 0, out_n, dirs)
    return keys, out_o, out_n, dirs


@numba.njit(**_JIT)
def on_upper(phase: float, weight: float, sample: int, golden: float) -> bool:
    """`baking.plan.Plan.on_upper` of one sample (the same float64 operations)."""
    return (phase + sample * golden) % 1.0 < weight


@numba.njit(**_JIT)
def level_paths(here: np.ndarray, below: np.ndarray, done: np.ndarray,
                remaining: np.ndarray, phase: np.ndarray, weight: np.ndarray,
                golden: float):
    """The pending paths of one isovalue level, sorted by texel, samples ascending.

    Args:
        here: (A,) sorted plan positions of texels whose lower level is this one (their
            samples on the lower level come here); below: (B,) sorted positions of texels
            whose lower level is the one below (their samples on the upper level).
        done, remaining: (T_all,) samples a texel has, and how many more it needs: its
            pending samples are ``done … done + remaining - 1``.
        phase, weight: the plan's (T_all,) level-assignment phases and upper weights.

    Returns:
        positions (P,) and sample indices (P,) of the paths, int64, and the (K,) sorted
        positions of the texels among them.
    """
    bound = 0
    for p in here:
        bound += remaining[p]
    for p in below:
        bound += remaining[p]
    pos = np.empty(bound, np.int64)
    samples = np.empty(bound, np.int64)
    texels = np.empty(len(here) + len(below), np.int64)
    count, k, a, b = 0, 0, 0, 0
    while a < len(here) or b < len(below):  # merge the two sorted lists
        upper = a == len(here) or (b < len(below) and below[b] < here[a])
        if upper:
            p = below[b]
            b += 1
        else:
            p = here[a]
            a += 1
        start = count
        for s in range(done[p], done[p] + remaining[p]):
            if on_upper(phase[p], weight[p], s, golden) == upper:
                pos[count] = p
                samples[count] = s
                count += 1
        if count > start:
            texels[k] = p
            k += 1
    return pos[:count], samples[:count], texels[:k]


@numba.njit(**_JIT)
def sincos_turns(u):
    """(cos 2πu, sin 2πu) for float32 u in [0, 1), in float32 to ~1e-7.

    The angle is cut into quarter turns, each rotated about its middle (|x| ≤ π/4), where
    Taylor series to x⁹ (sine) and x⁸ (cosine) are exact to 2e-9 and 3e-8; four times
    cheaper than the libm calls, which were most of a cosine-sampled direction's cost.
    """
    quarter = np.float32(4.0) * u
    q = np.int64(quarter)
    x = (quarter - np.float32(q) - np.float32(0.5)) * np.float32(0.5 * math.pi)
    x2 = x * x
    s = x * (np.float32(1.0) + x2 * (np.float32(-1.0 / 6) + x2 * (np.float32(1.0 / 120) + x2 * (
        np.float32(-1.0 / 5040) + x2 * np.float32(1.0 / 362880)))))
    c = np.float32(1.0) + x2 * (np.float32(-0.5) + x2 * (np.float32(1.0 / 24) + x2 * (
        np.float32(-1.0 / 720) + x2 * np.float32(1.0 / 40320))))
    half = np.float32(math.sqrt(0.5))  # the quarter's middle, π/4: cos = sin = √½
    cq, sq = half * (c - s), half * (c + s)  # cos, sin of the angle within the quarter
    # turned by q quarters without branches (they mispredict: q is random): odd quarters
    # swap the pair, the second half-turn negates it
    odd = np.float32(q & 1)
    sign = np.float32(1 - 2 * (q >> 1))
    return sign * (cq - odd * (sq + cq)), sign * (sq + odd * (cq - sq))


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def _fill_cosine_directions(keys: np.ndarray, dim: int, normals: np.ndarray,
                            out: np.ndarray) -> None:
    """out[:] = `cosine_directions` (keys, dim, normals)."""
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    for i in range(len(keys)):
        lx, ly, lz = _cosine_local(keys[i], k0, k1)
        nx, ny, nz = normals[0, i], normals[1, i], normals[2, i]
        tx, ty, tz, bx, by, bz = _frame(nx, ny, nz)
        out[0, i] = lx * tx + ly * bx + lz * nx
        out[1, i] = lx * ty + ly * by + lz * ny
        out[2, i] = lx * tz + ly * bz + lz * nz


@numba.njit(**_JIT)
def _cosine_local(key: np.uint32, k0: np.uint64, k1: np.uint64):
    """The cosine-distributed direction of a key (dimension keys k0, k1) in the frame
    whose z axis is the normal (Malley's method), float32."""
    u0, u1 = uniform_f32(key, k0), uniform_f32(key, k1)
    r = np.sqrt(u0)
    c, si = sincos_turns(u1)
    return r * c, r * si, np.sqrt(np.float32(1.0) - u0)


@numba.njit(**_JIT)
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
    hits = 0
    for i in range(len(prim)):
        hits += prim[i] >= 0
    new_pos = np.empty((3, hits), np.float32)
    new_n = np.empty((3, hits), np.float32)
    new_beta = np.empty((3, hits), np.float32)
    new_keys = np.empty(hits, np.uint32)
    new_alive = np.empty(hits, np.int64)
    j = 0
    for i in range(len(prim)):
        if prim[i] < 0:
            continue
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
        j += 1
    new_dirs = np.empty((3, hits), np.float32)
    _fill_cosine_directions(new_keys, dim, new_n, new_dirs)
    return new_pos, new_n, new_beta, new_dirs, new_keys, new_alive


@numba.njit(**_JIT)
def add_escaped(result: np.ndarray, alive: np.ndarray, prim: np.ndarray,
                beta: np.ndarray, radiance: np.ndarray) -> None:
    """result[alive[i], :3] += beta[:, i] · radiance for every ray i that escaped
    (``prim < 0``): a constant environment seen by a cosine-sampled ray, where
    `radiance` (3,) is π·L (nothing to do when it is zero); beta (3, M)."""
    if radiance[0] == 0 and radiance[1] == 0 and radiance[2] == 0:
        return
    for i in range(len(prim)):
        if prim[i] < 0:
            row = alive[i]
            for c in range(3):
                result[row, c] += beta[c, i] * radiance[c]


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
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



# -- the procedural sky (`baking.environment.SkyEnvironment`), compiled --------------------
SKY_PARAMS = 19
"""Length of `sky_params`: zenith, horizon, ground (3 each), sin(horizon blur), sun
direction (3), cos(sun radius), sun radiance (3), sun probability, 1/(sun cone solid
angle)."""


def sky_params(env) -> np.ndarray:
    """(SKY_PARAMS,) float64 description of a `SkyEnvironment` for the sky kernels."""
    cone = 2.0 * math.pi * (1.0 - env.sun_cos_radius)
    return np.concatenate([
        env.zenith, env.horizon, env.ground, [math.sin(math.radians(env.horizon_blur))],
        env.sun_direction, [env.sun_cos_radius], env.sun_radiance, [env.sun_probability],
        [1.0 / cone if cone > 0 else 0.0],
    ]).astype(np.float64)


@numba.njit(**_JIT)
def _sky_tuple(p: np.ndarray) -> tuple:
    """The (SKY_PARAMS,) array as a tuple: helpers called per ray take it by value (an
    array argument costs reference counting on every call, ten times the helper's
    arithmetic). The helpers are inlined by numba itself (``inline="always"``): left to
    LLVM they stay calls, and the loops calling them do not vectorise (65 vs 22 ns per
    light sample)."""
    return (p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11], p[12],
            p[13], p[14], p[15], p[16], p[17], p[18])


@numba.njit(**_JIT, inline="always")
def _sky_sun(p: tuple, x: float, y: float, z: float) -> bool:
    """Is unit direction (x, y, z) inside the sun's cone? (No branch: it is random.)"""
    return (p[17] > 0) & (x * p[10] + y * p[11] + z * p[12] >= p[13])


@numba.njit(**_JIT, inline="always")
def _sky_pdf(p: tuple, x: float, y: float, z: float) -> float:
    """Density (1/sr) of the sky's sampler at unit direction (x, y, z)."""
    return (1.0 - p[17]) / (4.0 * math.pi) + (p[17] * p[18] if _sky_sun(p, x, y, z) else 0.0)


@numba.njit(**_JIT, inline="always")
def _sky_radiance(p: tuple, x: float, y: float, z: float):
    """(r, g, b) sky radiance arriving from unit direction (x, y, z)."""
    h = p[9]
    t = min(max((z + h) / (2 * h), 0.0), 1.0) if h > 0 else 0.0
    g = t * t * (3.0 - 2.0 * t) if h > 0 else (1.0 if z >= 0 else 0.0)
    sun = 1.0 if _sky_sun(p, x, y, z) else 0.0
    up = max(z, 0.0)
    return (g * (p[3] + (p[0] - p[3]) * up) + (1.0 - g) * p[6] + sun * p[14],
            g * (p[4] + (p[1] - p[4]) * up) + (1.0 - g) * p[7] + sun * p[15],
            g * (p[5] + (p[2] - p[5]) * up) + (1.0 - g) * p[8] + sun * p[16])


@numba.njit(**_JIT, inline="always")
def _sky_sample(p: tuple, sun_frame: tuple, u0: float, u1: np.float32):
    """The sky sampler's unit direction (x, y, z) for uniforms (u0, u1): the sun cone
    with probability p_sun, else the whole sphere (`SkyEnvironment.sample`); `sun_frame`
    is `_frame` of the sun direction, the angle's sine and cosine come from
    `sincos_turns` (u1 in single precision, below 1). Both candidates are computed and
    one is selected: a branch on the random u0 mispredicts every other time."""
    p_sun = p[17]
    c32, s32 = sincos_turns(u1)
    cos_phi, sin_phi = float(c32), float(s32)
    cos_t = 1.0 - (u0 / max(p_sun, 1e-300)) * (1.0 - p[13])
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    tx, ty, tz, bx, by, bz = sun_frame
    cx, cy = sin_t * cos_phi, sin_t * sin_phi
    v = min((u0 - p_sun) / (1.0 - p_sun), 1.0 - 2.0**-53)
    z = 1.0 - 2.0 * v
    rho = math.sqrt(max(0.0, 1.0 - z * z))
    in_sun = u0 < p_sun
    return (cx * tx + cy * bx + cos_t * p[10] if in_sun else rho * cos_phi,
            cx * ty + cy * by + cos_t * p[11] if in_sun else rho * sin_phi,
            cx * tz + cy * bz + cos_t * p[12] if in_sun else z)


@numba.njit(**_JIT)
def sky_light_samples(p: np.ndarray, keys: np.ndarray, dim: int, normals: np.ndarray):
    """One importance-sampled sky direction per path vertex, MIS-weighted against cosine
    sampling (power heuristic), as `integrator._direct_env` does with numpy.

    Args:
        keys: (M,) path keys; normals: (3, M) unit normals of the vertices.

    Returns:
        dirs (3, M) float32, contributions (3, M) float64 = L·cos·w/pdf (to be multiplied
        by the throughput where the shadow ray is not blocked; zero where not useful), and
        useful (M,) bool (cos > 0 and pdf > 0).
    """
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    m = len(keys)
    dirs = np.empty((3, m), np.float32)
    contrib = np.empty((3, m))
    useful = np.empty(m, np.bool_)
    sun_frame = _frame(p[10], p[11], p[12])
    p = _sky_tuple(p)
    for i in range(m):  # no branches: the loop runs at 26 ns per vertex instead of 65
        x, y, z = _sky_sample(p, sun_frame, uniform31(keys[i], k0), uniform_f32(keys[i], k1))
        dirs[0, i], dirs[1, i], dirs[2, i] = x, y, z
        cos = normals[0, i] * x + normals[1, i] * y + normals[2, i] * z
        pdf = _sky_pdf(p, x, y, z)
        ok = (cos > 0) & (pdf > 0)
        useful[i] = ok
        other = cos / math.pi
        scale = cos * pdf / (pdf * pdf + other * other) if ok else 0.0  # L·cos·w/pdf
        r, g, b = _sky_radiance(p, x, y, z)
        contrib[0, i], contrib[1, i], contrib[2, i] = r * scale, g * scale, b * scale
    return dirs, contrib, useful


@numba.njit(**_JIT)
def shadow_rays(useful: np.ndarray, pos: np.ndarray, dirs: np.ndarray):
    """The shadow rays of the (M,) `useful` light samples of vertices at (3, M) `pos`
    towards (3, M) `dirs`: their indices (K,) int64, origins (3, K) and directions
    (3, K), float32."""
    idx = np.flatnonzero(useful)
    origins = np.empty((3, len(idx)), np.float32)
    out = np.empty((3, len(idx)), np.float32)
    for j in range(len(idx)):
        for c in range(3):
            origins[c, j] = pos[c, idx[j]]
            out[c, j] = dirs[c, idx[j]]
    return idx, origins, out


@numba.njit(**_JIT)
def add_unblocked(result: np.ndarray, alive: np.ndarray, idx: np.ndarray,
                  blocked: np.ndarray, beta: np.ndarray, contrib: np.ndarray) -> None:
    """result[alive[idx[j]], :3] += beta[:, idx[j]]·contrib[:, idx[j]] for every shadow
    ray j that is not `blocked` (beta, contrib: (3, M))."""
    for j in range(len(idx)):
        if blocked[j]:
            continue
        i = idx[j]
        for c in range(3):
            result[alive[i], c] += beta[c, i] * contrib[c, i]


@numba.njit(**_JIT)
def sky_add_escaped(p: np.ndarray, result: np.ndarray, alive: np.ndarray, prim: np.ndarray,
                    beta: np.ndarray, dirs: np.ndarray, normals: np.ndarray) -> None:
    """result[alive[i], :3] += beta[:, i]·L(dir)·π·w for every cosine-sampled ray i that
    escaped (prim < 0), w the power-heuristic weight against the sky's light sample
    (beta, dirs, normals: (3, M))."""
    p = _sky_tuple(p)
    m = len(prim)
    added = np.empty((3, m))
    for i in range(m):  # without branches, in SIMD lanes; hits get zero
        x, y, z = float(dirs[0, i]), float(dirs[1, i]), float(dirs[2, i])
        cos = normals[0, i] * x + normals[1, i] * y + normals[2, i] * z
        own, pdf = cos / math.pi, _sky_pdf(p, x, y, z)
        total = own * own + pdf * pdf
        weight = math.pi * own * own / total if (total > 0) & (prim[i] < 0) else 0.0
        r, g, b = _sky_radiance(p, x, y, z)
        added[0, i], added[1, i], added[2, i] = r * weight, g * weight, b * weight
    for i in range(m):
        if prim[i] < 0:
            row = alive[i]
            for c in range(3):
                result[row, c] += beta[c, i] * added[c, i]


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
    path_starts(np.uint64(0), index, index, index, index, vec.T.copy(), vec.T.copy())
    level_paths(index, index, index, index, np.zeros(1), np.zeros(1), 0.5)
    sky = np.zeros(SKY_PARAMS)
    _, contrib, useful = sky_light_samples(sky, keys, 0, vec)
    idx, _, _ = shadow_rays(useful, vec, vec)
    add_unblocked(result, index, idx, np.zeros(len(idx), np.bool_), vec, contrib)
    sky_add_escaped(sky, result, index, prim, vec, vec, vec)
