"""A plan's per-texel work in compiled code, one call per work item and no Python — so no
wait for the GIL — between the texels: the gradients at the texels' centres
(`plan._gradients`), the reach tests (`plan._Reaches`: can a texel be moved onto its
level, and do its paths start on its lit side there?) and where a chunk's paths start
(`passes.LevelStarts.of`). Each is the float64 (and float32) operations of the array code
it stands for (`volumes.gradient_at`, `plan.landing_offsets`, `plan.landed_points`,
`plan.project_to_level`, `volumes.value_at`, `volumes.values_along_normals`,
`passes.start_points`), to the bit.
"""

from __future__ import annotations

import numba
import numpy as np

from isolume.baking.sampling_kernels import JIT
from isolume.volumes.field import (
    along_normals,
    gradient_lerp,
    newton_steps,
    normal_scratch,
    unit_normal,
    value_at_world,
)

LANDING_STEPS = 32_000
"""Steps of a landing offset per reach (`plan.landing_offsets`): int16 holds ±32 767, so an
offset of a whole reach keeps 2 % to spare for the float rounding of a clamped move."""
UNLANDED = np.iinfo(np.int16).min
"""The landing offset of a level a texel does not use (`Plan.landing`)."""
CONVERGED_FRACTION = 0.1
"""A texel reaches a level when |ρ(p) − L| ends below this fraction of the level spacing."""
NEWTON_ITERATIONS = 4
"""`plan.project_to_level`'s default, which the reach tests project with."""


@numba.njit(**JIT)
def _centre(shape: np.ndarray, lo: np.ndarray, texel_size: np.ndarray, flat: int,
            out: np.ndarray) -> None:
    """out (3,) = the world xyz centre of texel `flat` (`LatticeGeometry.centres`)."""
    layer = shape[1] * shape[2]
    k = flat // layer
    j = (flat - k * layer) // shape[2]
    i = flat - k * layer - j * shape[2]
    out[0] = lo[0] + (i + 0.5) * texel_size[0]
    out[1] = lo[1] + (j + 0.5) * texel_size[1]
    out[2] = lo[2] + (k + 0.5) * texel_size[2]


@numba.njit(**JIT)
def gradient_norms(shape: np.ndarray, lo: np.ndarray, texel_size: np.ndarray,
                   ids: np.ndarray, data: np.ndarray, w: np.ndarray, inverse: np.ndarray,
                   origin: np.ndarray, spacing: np.ndarray, h: float, out: np.ndarray) -> None:
    """out (N,) = |∇ρ| × `h` at the centres of the (N,) texels `ids` (value units per `h`
    world units): ``np.linalg.norm(volumes.gradient_at(volume, centres), axis=1) * h`` —
    the gradient as float32, its float32 length times `h` in float32, as numpy computes
    it — with the stencil of `volumes.normal_stencil`."""
    corners = np.empty((8, 3), np.float32)
    window = np.empty((4, 4, 4), np.float32)
    g = np.empty(3)
    centre = np.empty(3)
    scale = np.float32(h)
    for r in range(len(ids)):
        _centre(shape, lo, texel_size, ids[r], centre)
        gradient_lerp(data, w, inverse, (centre[2] - origin[2]) / spacing[2],
                      (centre[1] - origin[1]) / spacing[1], (centre[0] - origin[0]) / spacing[0],
                      corners, window, g)
        gx, gy, gz = np.float32(g[0]), np.float32(g[1]), np.float32(g[2])
        out[r] = np.sqrt(gx * gx + gy * gy + gz * gz) * scale


@numba.njit(**JIT)
def _encode(point: np.ndarray, centre: np.ndarray, reach: float, out: np.ndarray) -> None:
    """out (3,) int16 = `plan.landing_offsets` of one point from its texel's centre."""
    scale = LANDING_STEPS / reach
    steps = np.empty(3)
    missing = False
    for a in range(3):
        steps[a] = (point[a] - centre[a]) * scale
        missing |= steps[a] != steps[a]
    for a in range(3):
        out[a] = UNLANDED if missing else np.int16(
            np.rint(min(max(steps[a], -LANDING_STEPS), LANDING_STEPS)))


@numba.njit(**JIT)
def landed_starts(shape: np.ndarray, lo: np.ndarray, texel_size: np.ndarray,
                  ids: np.ndarray, texels: np.ndarray, upper: np.ndarray,
                  landing: np.ndarray, step: float, high: np.ndarray, lift: float,
                  data: np.ndarray, w: np.ndarray, inverse: np.ndarray, origin: np.ndarray,
                  spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start points and normals of the (N,) plan positions `texels` (`passes.start_points`
    at their landings).

    Args:
        shape: (3,) int64 lattice shape (Z, Y, X); lo, texel_size: (3,) float64 world xyz
            (`LatticeGeometry`).
        ids: (T,) flat lattice ids of the plan's texels; texels: (N,) positions into them.
        upper: (N,) bool, the level is the texel's upper one (its landing's side).
        landing: (T, 2, 3) int16 `Plan.landing` offsets, in units of `step` world units.
        high: (T,) bool `Plan.high`; lift: the start point's offset off the surface,
            world units (``config.offset · h``).
        data, w, inverse, origin, spacing: the normals' stencil (`volumes.normal_stencil`).

    Returns:
        origins (N, 3) and normals (N, 3) float32 (NaN where a texel has no landing).
    """
    n = len(texels)
    origins = np.empty((n, 3), np.float32)
    normals = np.empty((n, 3), np.float32)
    scratch = normal_scratch()
    unit = np.empty(3, np.float32)
    centre = np.empty(3)
    point = np.empty(3)
    for r in range(n):
        t = texels[r]
        side = 1 if upper[r] else 0
        _centre(shape, lo, texel_size, ids[t], centre)
        for a in range(3):
            point[a] = (np.nan if landing[t, side, 0] == UNLANDED
                        else centre[a] + landing[t, side, a] * step)
        unit_normal(data, w, inverse, origin, spacing, point[0], point[1], point[2], False,
                    scratch, unit)
        for a in range(3):
            normal = -np.float64(unit[a]) if high[t] else np.float64(unit[a])
            origins[r, a] = np.float32(point[a] + lift * normal)
            normals[r, a] = np.float32(normal)
    return origins, normals


@numba.njit(**JIT)
def reach_tests(shape: np.ndarray, lo: np.ndarray, texel_size: np.ndarray,
                ids: np.ndarray, lower: np.ndarray, levels: np.ndarray, side: int,
                high: np.ndarray, which: np.ndarray, landing: np.ndarray, ok: np.ndarray,
                moved: np.ndarray, reach: float, lift: float, cube: np.ndarray,
                data: np.ndarray, newton_w: np.ndarray, lift_w: np.ndarray,
                inverse: np.ndarray, origin: np.ndarray, spacing: np.ndarray,
                scratch: np.ndarray, first: int, stop: int) -> None:
    """The reach tests (`plan._Reaches`) of the texels first … stop − 1 where `which`
    (T,) bool: each is moved from its centre onto its lower (`side` 0) or upper (1) level
    — its landing in `landing` (T, 3) int16 (that side's `Plan.landing`), projected here
    by Newton steps (`NEWTON_ITERATIONS`, the smoothed gradient, at most `reach` world
    units) and written there where it has none — and ``ok`` (T,) is set where it lands
    within `CONVERGED_FRACTION` of its level spacing of the level and, when `lift` > 0,
    the point `lift` world units along its lit side's normal (`high` (T,): the high
    side; the bake's normals) lies on that side (its paths start outside the level);
    ``moved`` (T,) gets the move's length, world units.

    Args:
        ids, lower: (T,) flat lattice ids and lower level indices; levels: (K,) isovalues.
        cube: the volume's (Z, Y, X, 1) samples; data: its (Z, Y, X) samples; newton_w,
            lift_w: the stencil weights of Newton's gradient (smoothed) and of the lit
            side's normal (the bake's); inverse: (3,) 1 / (2 h); origin, spacing: (3,).
        scratch: (1,) of `volumes.value_at`'s result type.
    """
    centre = np.empty(3)
    count = stop - first
    # the texels without a landing yet, projected together (one Newton call)
    todo = np.empty(count, np.int64)
    n = 0
    for t in range(first, stop):
        if which[t] and landing[t, 0] == UNLANDED:
            todo[n] = t
            n += 1
    if n:
        starts = np.empty((n, 3))
        targets = np.empty(n)
        for r in range(n):
            _centre(shape, lo, texel_size, ids[todo[r]], starts[r])
            targets[r] = levels[lower[todo[r]] + side]
        projected = np.empty((n, 3))
        newton_steps(cube, data, newton_w, inverse, origin, spacing, starts, targets, reach,
                     NEWTON_ITERATIONS, projected)
        for r in range(n):
            _encode(projected[r], starts[r], reach, landing[todo[r]])
    # every texel asked: its landing, the level check, its move; the lit-side check's
    # points gathered by side (one call each)
    landed = np.empty((count, 3))
    lifted = np.empty(count, np.int64)
    m = 0
    for t in range(first, stop):
        if not which[t]:
            continue
        _centre(shape, lo, texel_size, ids[t], centre)
        for a in range(3):
            landed[t - first, a] = (np.nan if landing[t, 0] == UNLANDED
                                    else centre[a] + landing[t, a] * (reach / LANDING_STEPS))
        x, y, z = landed[t - first, 0], landed[t - first, 1], landed[t - first, 2]
        level = levels[lower[t] + side]
        tol = CONVERGED_FRACTION * (levels[lower[t] + 1] - levels[lower[t]])
        reached = (x == x and y == y and z == z and abs(
            value_at_world(cube, origin, spacing, x, y, z, scratch) - level) <= tol)
        ok[t] = reached
        if reached and lift > 0:
            lifted[m] = t
            m += 1
        dx, dy, dz = x - centre[0], y - centre[1], z - centre[2]
        moved[t] = np.sqrt(dx * dx + dy * dy + dz * dz)
    for flip in (False, True):
        rows = np.empty(m, np.int64)
        k = 0
        for r in range(m):
            if high[lifted[r]] == flip:
                rows[k] = lifted[r]
                k += 1
        if k == 0:
            continue
        points = np.empty((k, 3))
        for r in range(k):
            points[r] = landed[rows[r] - first]
        beyond = np.empty(k)
        along_normals(cube, data, lift_w, inverse, origin, spacing, points, lift,
                      1.0 if flip else -1.0, beyond)
        for r in range(k):
            t = rows[r]
            ok[t] = beyond[r] - levels[lower[t] + side] > 0 if flip else \
                beyond[r] - levels[lower[t] + side] < 0
