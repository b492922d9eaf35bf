"""Compiled loops between Embree calls: ray generation, hit processing, accumulation.

The path tracer spends its time in two places: inside Embree, and in the per-ray
arithmetic between Embree calls (random numbers, cosine-sampled directions, the next path
vertex). Written as numpy expressions the second part costs about as much as Embree
itself, makes a dozen temporaries per ray and holds the GIL often enough that worker
threads queue for it. These numba kernels do it in one pass per stage without the GIL
(``nogil=True``), so worker threads overlap fully with each other and with Embree.

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
def uniform2(keys: np.ndarray, dim: int) -> np.ndarray:
    """(N, 2) float64 uniforms of dimensions `dim`, `dim + 1` (`baking.rng.uniform2`)."""
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    out = np.empty((len(keys), 2))
    for i in range(len(keys)):
        out[i, 0] = uniform(keys[i], k0)
        out[i, 1] = uniform(keys[i], k1)
    return out


@numba.njit(**_JIT)
def path_starts(seed_key: np.uint64, ids: np.ndarray, pos: np.ndarray, samples: np.ndarray,
                texels: np.ndarray, origins: np.ndarray, normals: np.ndarray):
    """Keys, origins and normals of P paths (texel positions `pos`, sorted, and sample
    indices), from the per-texel start points of one level.

    Args:
        seed_key: ``pcg_hash(seed)``; ids: (T_all,) flat lattice index of each position.
        texels: (T,) sorted positions that `origins`, `normals` (T, 3) belong to; every
            value of `pos` is among them.

    Returns:
        keys (P,) uint32 (`baking.rng.path_keys`), origins (P, 3), normals (P, 3).
    """
    count = len(pos)
    keys = np.empty(count, np.uint32)
    out_o = np.empty((count, 3), np.float32)
    out_n = np.empty((count, 3), np.float32)
    j = 0
    for i in range(count):
        while texels[j] < pos[i]:  # both sorted: one merge pass
            j += 1
        h = pcg_hash(np.uint64(np.uint32(ids[pos[i]])) ^ seed_key)
        keys[i] = np.uint32(pcg_hash((h + np.uint64(samples[i]) * _GOLDEN) & _MASK))
        for c in range(3):
            out_o[i, c] = origins[j, c]
            out_n[i, c] = normals[j, c]
    return keys, out_o, out_n


@numba.njit(**_JIT, fastmath=True)
def cosine_directions(keys: np.ndarray, dim: int, normals: np.ndarray) -> np.ndarray:
    """(N, 3) float32 world directions, cosine-distributed about the (N, 3) float32 unit
    normals, from the uniforms of dimensions `dim`, `dim + 1` of the (N,) uint32 keys.

    Malley's method (a uniform disk point lifted to the hemisphere) in the frame of Duff
    et al. 2017, like `sampling.sample_cosine_hemisphere` followed by `sampling.to_world`,
    in single precision (the trigonometry is most of the cost; Embree is float32 too).
    """
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    one, two_pi = np.float32(1.0), np.float32(2.0 * math.pi)
    out = np.empty((len(keys), 3), np.float32)
    for i in range(len(keys)):
        u0, u1 = np.float32(uniform(keys[i], k0)), np.float32(uniform(keys[i], k1))
        r, phi = np.sqrt(u0), two_pi * u1
        lx, ly, lz = r * np.cos(phi), r * np.sin(phi), np.sqrt(max(np.float32(0.0), one - u0))
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        sign = one if nz >= 0 else -one
        a = -one / (sign + nz)
        b = nx * ny * a
        tx, ty, tz = one + sign * nx * nx * a, sign * b, -sign * nx
        bx, by, bz = b, sign + ny * ny * a, -ny
        out[i, 0] = lx * tx + ly * bx + lz * nx
        out[i, 1] = lx * ty + ly * by + lz * ny
        out[i, 2] = lx * tz + ly * bz + lz * nz
    return out


@numba.njit(**_JIT)
def next_vertices(pos: np.ndarray, dirs: np.ndarray, t: np.ndarray, ng: np.ndarray,
                  prim: np.ndarray, beta: np.ndarray, albedo: np.ndarray,
                  offset: float):
    """The path vertices where the (N,) rays hit (``prim >= 0``), ready to continue.

    Each hit point p = pos + t·dir (float32, like Embree's own) is pushed `offset` (world
    units) off the facet along its geometric normal, turned towards the arriving ray
    (bounce vertices use the facet normal: a smoothed normal would send some directions
    into the facet at grazing angles, where rays starting this close to it can slip
    between triangles). Throughputs are multiplied by the (3,) albedo.

    Returns:
        rows (H,) int64 indices of the hitting rays, positions (H, 3), unit normals
        (H, 3) and throughputs (H, 3), all float32.
    """
    hits = 0
    for i in range(len(prim)):
        hits += prim[i] >= 0
    rows = np.empty(hits, np.int64)
    new_pos = np.empty((hits, 3), np.float32)
    new_n = np.empty((hits, 3), np.float32)
    new_beta = np.empty((hits, 3), np.float32)
    j = 0
    for i in range(len(prim)):
        if prim[i] < 0:
            continue
        gx, gy, gz = ng[i, 0], ng[i, 1], ng[i, 2]
        facing = gx * dirs[i, 0] + gy * dirs[i, 1] + gz * dirs[i, 2]
        scale = np.float32(-1.0 if facing > 0 else 1.0) / max(
            np.float32(math.sqrt(gx * gx + gy * gy + gz * gz)), np.float32(1e-30))
        for c in range(3):
            normal = ng[i, c] * scale
            new_n[j, c] = normal
            new_pos[j, c] = (pos[i, c] + t[i] * dirs[i, c]) + np.float32(offset) * normal
            new_beta[j, c] = beta[i, c] * albedo[c]
        rows[j] = i
        j += 1
    return rows, new_pos, new_n, new_beta


@numba.njit(**_JIT)
def add_escaped(result: np.ndarray, alive: np.ndarray, prim: np.ndarray,
                beta: np.ndarray, radiance: np.ndarray) -> None:
    """result[alive[i], :3] += beta[i] · radiance for every ray i that escaped
    (``prim < 0``): a constant environment seen by a cosine-sampled ray, where
    `radiance` (3,) is π·L."""
    for i in range(len(prim)):
        if prim[i] < 0:
            row = alive[i]
            for c in range(3):
                result[row, c] += beta[i, c] * radiance[c]


@numba.njit(**_JIT)
def texel_sums(pos: np.ndarray, estimates: np.ndarray, weights: np.ndarray):
    """Per-texel sums of the path estimates, for paths sorted by texel position.

    Args:
        pos: (P,) texel positions, sorted (equal positions adjacent).
        estimates: (P, C) per-path estimates.
        weights: (C,) luminance weights for the second moment (zeros but the first
            for SH transfer).

    Returns:
        positions (T,), sums (T, C), second moments Σ lum² (T,), counts (T,).
    """
    texels = 0
    for i in range(len(pos)):
        texels += i == 0 or pos[i] != pos[i - 1]
    channels = estimates.shape[1]
    positions = np.empty(texels, pos.dtype)
    sums = np.zeros((texels, channels))
    second = np.zeros(texels)
    counts = np.zeros(texels, np.int64)
    j = -1
    for i in range(len(pos)):
        if i == 0 or pos[i] != pos[i - 1]:
            j += 1
            positions[j] = pos[i]
        lum = 0.0
        for c in range(channels):
            sums[j, c] += estimates[i, c]
            lum += weights[c] * estimates[i, c]
        second[j] += lum * lum
        counts[j] += 1
    return positions, sums, second, counts


def warm_up() -> None:
    """Load (or compile, the first time on a machine) every kernel for the argument types
    the path tracer uses, so that the first bake's timings measure tracing only."""
    keys = np.zeros(1, np.uint32)
    vec = np.ones((1, 3), np.float32)
    prim = np.zeros(1, np.int32)
    dirs = cosine_directions(keys, 0, vec)
    next_vertices(vec, dirs, np.ones(1, np.float32), vec, prim, vec, np.ones(3, np.float32),
                  1e-3)
    add_escaped(np.zeros((1, 3)), np.zeros(1, np.int64), prim, vec, np.ones(3))
    texel_sums(np.zeros(1, np.int64), np.zeros((1, 3)), np.ones(3))
    index = np.zeros(1, np.int64)
    path_starts(np.uint64(0), index, index, index, index, vec, vec)
