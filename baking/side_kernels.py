"""Side probes in one compiled call per work item (`baking.sides.open_rays`): the probe
origins, their rays, Embree called per ray (`embree_kernels.occluded_rays`), the open
counts and the on-side test, with no Python — and so no wait for the GIL — between them.
The same numbers as the array code `baking.sides` runs where a scene has no compiled
calls (`trace.EmbreeCalls`).
"""

from __future__ import annotations

import numba
import numpy as np

from isolume.baking.embree_kernels import occluded_rays
from isolume.baking.kernels import path_starts
from isolume.baking.sampling_kernels import JIT
from isolume.volumes.field import value_at_world


@numba.njit(**JIT)
def open_counts(calls: tuple[int, ...], key: np.uint32, ids: np.ndarray, points: np.ndarray,
                normals: np.ndarray, offset: float, sign: float, which: np.ndarray,
                cube: np.ndarray, origin: np.ndarray, spacing: np.ndarray,
                level: float, scratch: np.ndarray, probes: int) -> np.ndarray:
    """(N,) int64: how many of `probes` rays from each point where `which` (N,) bool meet
    nothing; 0 elsewhere, and where the probes' origin does not lie on their side.

    Args:
        calls: the level scene's `trace.EmbreeCalls`; key: the probes' seed key.
        ids: (N,) int64 flat lattice ids (the paths' keys: samples 0 … probes − 1).
        points: (N, 3) float64 world points on the level; normals: (N, 3) float64 unit
            normals towards low values.
        offset, sign: the origins are ``points + sign · offset · normals`` (world units),
            the rays cosine-distributed about ``sign · normals``; ``sign`` > 0: the low
            side, whose origins must have values below `level`, else above.
        cube: the volume's (Z, Y, X, 1) samples; origin, spacing: (3,) float64, world xyz.
        level: the isovalue in `scratch`'s type, (1,) that of `volumes.value_at`.
    """
    n = len(ids)
    out = np.zeros(n, np.int64)
    rows = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if which[i]:
            x = points[i, 0] + sign * offset * normals[i, 0]
            y = points[i, 1] + sign * offset * normals[i, 1]
            z = points[i, 2] + sign * offset * normals[i, 2]
            if x != x or y != y or z != z:
                continue
            beyond = value_at_world(cube, origin, spacing, x, y, z, scratch) - level
            if (beyond < 0) if sign > 0 else (beyond > 0):
                rows[m] = i
                m += 1
    if m == 0:
        return out
    starts = np.empty((m, 3), np.float32)
    dirs = np.empty((m, 3), np.float32)
    picked = np.empty(m, np.int64)
    for r in range(m):
        i = rows[r]
        picked[r] = ids[i]
        for c in range(3):
            starts[r, c] = np.float32(points[i, c] + sign * offset * normals[i, c])
            dirs[r, c] = np.float32(sign * normals[i, c])
    texels = np.arange(m)
    pos = np.empty(m * probes, np.int64)
    samples = np.empty(m * probes, np.int64)
    for r in range(m):
        for s in range(probes):
            pos[r * probes + s] = r
            samples[r * probes + s] = s
    _, ray_origins, _, ray_dirs = path_starts(key, picked, pos, samples, texels, starts, dirs)
    blocked = occluded_rays(calls, ray_origins, ray_dirs)
    for r in range(m):
        hit = 0
        for s in range(probes):
            hit += blocked[r * probes + s]
        out[rows[r]] = probes - hit
    return out
