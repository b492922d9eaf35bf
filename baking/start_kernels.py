"""Where a chunk's paths start, in one compiled call (`passes.LevelStarts.of`): each
texel's centre, its landing on the level (`plan.landed_points`), the normal of its lit
side there (`volumes.normals_at`, negated where it is lit on the high side) and the start
point lifted off the surface — the float64 operations of `passes.start_points`, to the
bit, with no Python (and so no wait for the GIL) between the texels.
"""

from __future__ import annotations

import numba
import numpy as np

from isolume.baking.plan import UNLANDED
from isolume.baking.sampling_kernels import JIT
from isolume.volumes.field import normal_scratch, unit_normal


@numba.njit(**JIT)
def landed_starts(shape: np.ndarray, lo: np.ndarray, texel_size: np.ndarray,
                  ids: np.ndarray, texels: np.ndarray, upper: np.ndarray,
                  landing: np.ndarray, step: float, high: np.ndarray, lift: float,
                  data: np.ndarray, w: np.ndarray, inverse: np.ndarray, origin: np.ndarray,
                  spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start points and normals of the (N,) plan positions `texels`.

    Args:
        shape: (3,) int64 lattice shape (Z, Y, X); lo, texel_size: (3,) float64 world xyz
            (`LatticeGeometry`).
        ids: (T,) flat lattice ids of the plan's texels; texels: (N,) positions into them.
        upper: (N,) bool, the level is the texel's upper one (its landing's side).
        landing: (T, 2, 3) int16 `Plan.landing` offsets, in units of `step` world units.
        high: (T,) bool `Plan.high`; lift: the start point's offset off the surface,
            world units (``config.offset · h``).
        data, w, inverse, origin, spacing: the normals' stencil (`volumes.field`).

    Returns:
        origins (N, 3) and normals (N, 3) float32 (NaN where a texel has no landing).
    """
    n = len(texels)
    origins = np.empty((n, 3), np.float32)
    normals = np.empty((n, 3), np.float32)
    scratch = normal_scratch()
    unit = np.empty(3, np.float32)
    layer = shape[1] * shape[2]
    point = np.empty(3)
    for r in range(n):
        t = texels[r]
        flat = ids[t]
        k = flat // layer
        j = (flat - k * layer) // shape[2]
        i = flat - k * layer - j * shape[2]
        side = 1 if upper[r] else 0
        for a, index in enumerate((i, j, k)):
            centre = lo[a] + (index + 0.5) * texel_size[a]
            point[a] = (np.nan if landing[t, side, 0] == UNLANDED
                        else centre + landing[t, side, a] * step)
        unit_normal(data, w, inverse, origin, spacing, point[0], point[1], point[2], False,
                    scratch, unit)
        for a in range(3):
            normal = -np.float64(unit[a]) if high[t] else np.float64(unit[a])
            origins[r, a] = np.float32(point[a] + lift * normal)
            normals[r, a] = np.float32(normal)
    return origins, normals
