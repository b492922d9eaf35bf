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
itself, per ray (`intersect_rays`, `occluded_rays`, through the addresses in
`trace.EmbreeCalls`): no Python, and so no wait for the GIL, between a chunk's rays.

They mirror, and are tested against, the numpy reference functions: `pcg_hash` and
`uniform` against `baking.rng` (bit for bit), `cosine_directions` against
`baking.sampling.sample_cosine_hemisphere` + `to_world`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

_JIT = {"nogil": True, "cache": True, "error_model": "numpy"}
DIMS_PER_VERTEX = 4  # 2 for the cosine-sampled direction, 2 for the light sample

_MULT = np.uint32(747796405)
_INC = np.uint32(2891336453)
_M2 = np.uint32(277803737)
_GOLDEN = np.uint32(0x9E3779B9)
_INV_2_32 = 1.0 / 4294967296.0


@numba.njit(**_JIT)
def pcg_hash(x: np.uint32) -> np.uint32:
    """PCG-RXS-M-XS hash of a 32-bit word (`baking.rng.pcg_hash`).

    numba widens integer arithmetic to 64 bits; truncating every product and sum back to
    32 bits lets LLVM keep the hash in 32-bit lanes, eight to a vector register (the
    64-bit form, masked, vectorised four wide with emulated multiplies: 2.7× slower).
    """
    state = np.uint32(x * _MULT + _INC)
    shift = np.uint32((state >> np.uint32(28)) + np.uint32(4))
    word = np.uint32(np.uint32((state >> shift) ^ state) * _M2)
    return np.uint32((word >> np.uint32(22)) ^ word)


@numba.njit(**_JIT)
def dimension_key(dim: int) -> np.uint32:
    """The hash that selects random dimension `dim` (`baking.rng.uniform`)."""
    return pcg_hash(np.uint32(np.uint32(dim) + _GOLDEN))


@numba.njit(**_JIT)
def uniform(key: np.uint32, dim_key: np.uint32) -> float:
    """The uniform in [0, 1) of a path key and a dimension key (`baking.rng.uniform`)."""
    return float(pcg_hash(np.uint32(key ^ dim_key))) * _INV_2_32


@numba.njit(**_JIT)
def _top31(key: np.uint32, dim_key: np.uint32) -> np.int32:
    """The hash's top 31 bits as a signed 32-bit integer: it converts to floating point
    in vector lanes (an unsigned 64-bit one does not)."""
    return np.int32(pcg_hash(np.uint32(key ^ dim_key)) >> np.uint32(1))


@numba.njit(**_JIT)
def uniform31(key: np.uint32, dim_key: np.uint32) -> float:
    """`uniform` from the hash's top 31 bits, within 2^-32 of `uniform`."""
    return float(_top31(key, dim_key)) * 2.0**-31


@numba.njit(**_JIT)
def uniform_f32(key: np.uint32, dim_key: np.uint32) -> np.float32:
    """`uniform31` in single precision, strictly below 1 (clamped to the largest float32
    below 1, where rounding would reach 1). Converted to float32 directly: one rounding
    of the same exact value as through float64."""
    return min(np.float32(_top31(key, dim_key)) * np.float32(2.0**-31),
               np.float32(1.0 - 2.0**-24))


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
            keys[k] = pcg_hash(np.uint32(h + np.uint32(samples[k]) * _GOLDEN))
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
    q = np.floor(quarter)  # the quarter, 0 … 3, kept in floating point: integer
    # conversions leave vector lanes (numba widens them to 64 bits, which AVX2 lacks)
    x = (quarter - q - np.float32(0.5)) * np.float32(0.5 * math.pi)
    x2 = x * x
    s = x * (np.float32(1.0) + x2 * (np.float32(-1.0 / 6) + x2 * (np.float32(1.0 / 120) + x2 * (
        np.float32(-1.0 / 5040) + x2 * np.float32(1.0 / 362880)))))
    c = np.float32(1.0) + x2 * (np.float32(-0.5) + x2 * (np.float32(1.0 / 24) + x2 * (
        np.float32(-1.0 / 720) + x2 * np.float32(1.0 / 40320))))
    half = np.float32(math.sqrt(0.5))  # the quarter's middle, π/4: cos = sin = √½
    cq, sq = half * (c - s), half * (c + s)  # cos, sin of the angle within the quarter
    # turned by q quarters without branches (they mispredict: q is random): odd quarters
    # swap the pair, the second half-turn negates it
    half_turns = np.floor(np.float32(0.5) * q)
    odd = q - np.float32(2.0) * half_turns
    sign = np.float32(1.0) - np.float32(2.0) * half_turns
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
def _cosine_local(key: np.uint32, k0: np.uint32, k1: np.uint32):
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


@numba.njit(**_JIT)
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


def sky_without_sun(p: np.ndarray) -> np.ndarray:
    """`sky_params` of the same sky without its sun (no sun radiance, no sun sampling)."""
    out = np.array(p, np.float64)
    out[14:18] = 0.0
    return out


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
    for j in range(len(idx)):  # without branches: blocked rays add exactly 0
        i = idx[j]
        seen = np.float64(not blocked[j])
        for c in range(3):
            result[alive[i], c] += beta[c, i] * contrib[c, i] * seen


@numba.njit(**_JIT)
def sky_add_escaped(p: np.ndarray, result: np.ndarray, alive: np.ndarray, prim: np.ndarray,
                    beta: np.ndarray, dirs: np.ndarray, normals: np.ndarray,
                    mis: bool) -> None:
    """result[alive[i], :3] += beta[:, i]·L(dir)·π·w for every cosine-sampled ray i that
    escaped (prim < 0), w the power-heuristic weight against the sky's light sample when
    `mis` (the vertex took one), else 1 (beta, dirs, normals: (3, M))."""
    p = _sky_tuple(p)
    m = len(prim)
    added = np.empty((3, m))
    for i in range(m):  # without branches, in SIMD lanes; hits get zero
        x, y, z = float(dirs[0, i]), float(dirs[1, i]), float(dirs[2, i])
        cos = normals[0, i] * x + normals[1, i] * y + normals[2, i] * z
        own, pdf = cos / math.pi, _sky_pdf(p, x, y, z) if mis else 0.0
        total = own * own + pdf * pdf
        weight = math.pi * own * own / total if (total > 0) & (prim[i] < 0) else 0.0
        r, g, b = _sky_radiance(p, x, y, z)
        added[0, i], added[1, i], added[2, i] = r * weight, g * weight, b * weight
    for i in range(m):  # without branches: `added` is 0 for rays that hit
        row = alive[i]
        for c in range(3):
            result[row, c] += beta[c, i] * added[c, i]


# -- a chunk of paths in one compiled call, Embree called per ray --------------------------
_INVALID_ID = np.uint32(0xFFFFFFFF)  # RTC_INVALID_GEOMETRY_ID
_ALL_GEOMETRY = np.uint32(0xFFFFFFFF)  # a ray mask that every geometry passes
RAY_RECORD_ROWS = 7
"""Columns of a recording of traced rays: origin (3), direction (3), 1 for an occlusion
query (0: closest hit)."""


@intrinsic
def _call_embree(typingctx, function, scene, ray):
    """Call ``void function(RTCScene scene, RTCRay(Hit)* ray, NULL)``: `rtcIntersect1` or
    `rtcOccluded1` at address `function` (all three arguments are 64-bit integers)."""
    if not all(isinstance(t, types.Integer) and t.bitwidth == 64
               for t in (function, scene, ray)):
        return None

    def codegen(context, builder, signature, args):
        pointer = ir.IntType(8).as_pointer()
        callee = ir.FunctionType(ir.VoidType(), [pointer, pointer, pointer])
        target = builder.inttoptr(args[0], callee.as_pointer())
        builder.call(target, [builder.inttoptr(args[1], pointer),
                              builder.inttoptr(args[2], pointer), pointer(None)])
        return context.get_dummy_value()

    return types.void(function, scene, ray), codegen


@numba.njit(**_JIT, inline="always")
def _set_ray(ray, bits, ox, oy, oz, dx, dy, dz) -> None:
    """Fill an RTCRayHit (`ray` float32, `bits` its uint32 view) for a query from (ox, oy,
    oz) towards (dx, dy, dz), distances 0 … ∞, no hit yet."""
    ray[0], ray[1], ray[2], ray[3] = ox, oy, oz, np.float32(0.0)
    ray[4], ray[5], ray[6], ray[7] = dx, dy, dz, np.float32(0.0)
    ray[8] = np.float32(np.inf)
    bits[9], bits[10], bits[11] = _ALL_GEOMETRY, np.uint32(0), np.uint32(0)  # mask, id, flags
    bits[18], bits[19] = _INVALID_ID, _INVALID_ID  # geomID, instID[0]


@numba.njit(**_JIT)
def _ray_buffer():
    """An RTCRayHit (at most 96 bytes) on a 16-byte boundary: its float32 words, the same
    words as uint32, and its address."""
    storage = np.empty(40, np.float32)
    first = (16 - storage.ctypes.data % 16) % 16 // 4
    ray = storage[first:first + 24]
    return ray, ray.view(np.uint32), ray.ctypes.data


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def intersect_rays(calls: tuple, pos: np.ndarray, dirs: np.ndarray):
    """Closest hits of (3, M) float32 rays (distances 0 … ∞), Embree called per ray
    (`trace.EmbreeCalls`).

    Returns:
        t (M,) float32 distances, prim (M,) int32 triangle ids (-1: no hit), ng (M, 3)
        float32 unnormalised facet normals — as embreex's ``run(..., output=1)``.
    """
    scene, intersect, _ = calls
    ray, bits, address = _ray_buffer()
    m = pos.shape[1]
    t = np.empty(m, np.float32)
    prim = np.empty(m, np.int32)
    ng = np.empty((m, 3), np.float32)
    for i in range(m):
        _set_ray(ray, bits, pos[0, i], pos[1, i], pos[2, i], dirs[0, i], dirs[1, i],
                 dirs[2, i])
        _call_embree(intersect, scene, address)
        t[i] = ray[8]
        prim[i] = -1 if bits[18] == _INVALID_ID else np.int32(bits[17])
        ng[i, 0], ng[i, 1], ng[i, 2] = ray[12], ray[13], ray[14]
    return t, prim, ng


@numba.njit(**_JIT)
def occluded_rays(calls: tuple, pos: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(M,) bool: does anything block the (3, M) float32 rays (distances 0 … ∞)?"""
    scene, _, occluded = calls
    ray, bits, address = _ray_buffer()
    m = pos.shape[1]
    blocked = np.empty(m, np.bool_)
    for i in range(m):
        _set_ray(ray, bits, pos[0, i], pos[1, i], pos[2, i], dirs[0, i], dirs[1, i],
                 dirs[2, i])
        _call_embree(occluded, scene, address)
        blocked[i] = ray[8] < 0  # tfar becomes -inf when something is hit
    return blocked


@numba.njit(**_JIT)
def trace_chunk(calls: tuple, seed_key: np.uint32, ids: np.ndarray, pos: np.ndarray,
                samples: np.ndarray, texels: np.ndarray, origins: np.ndarray,
                normals: np.ndarray, bounces: int, albedo: np.ndarray, offset: float,
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
    level_paths(index, index, index, index, np.zeros(1), np.zeros(1), 0.5)
    sky = np.zeros(SKY_PARAMS)
    trace_chunk((0, 0, 0), np.uint32(0), index, index[:0], index[:0], index, vec.T.copy(),
                vec.T.copy(), 2, np.ones(3, np.float32), 1e-3, np.ones(3), sky, sky, True, True,
                np.ones(3), np.zeros((1, 3)), np.zeros(1), index.copy(),
                np.empty((0, RAY_RECORD_ROWS), np.float32))
    _, contrib, useful = sky_light_samples(sky, keys, 0, vec)
    idx, _, _ = shadow_rays(useful, vec, vec)
    add_unblocked(result, index, idx, np.zeros(len(idx), np.bool_), vec, contrib)
    sky_add_escaped(sky, result, index, prim, vec, vec, vec, True)
