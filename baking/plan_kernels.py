"""A plan's per-texel work in compiled code, one call per work item and no Python — so no
wait for the GIL — between the texels: the gradients at the texels' centres
(`plan._gradients`), the reach tests (`plan._Reaches`: can a texel be moved onto its
level, and do its paths start on its lit side there?) and where a chunk's paths start
(`passes.LevelStarts.of`). Each is the float64 (and float32) operations of the array code
it stands for (`volumes.gradient_at`, `plan.landing_offsets`, `plan.landed_points`,
`plan.project_to_level`, `volumes.value_at`, `volumes.values_along_normals`,
`passes.start_points`), to the bit.

The kernels take a lattice as ``(shape, lo, texel_size)`` (`lattice_arrays`) and a volume
as ``(cube, data, inverse, origin, spacing)`` (`field_arrays`), with the weights of the
gradient's stencil apart (`volumes.field.normal_stencil`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

from isolume.volumes.field import (
    JIT,
    PART,
    along_normals,
    gradient_lerp,
    newton_steps,
    normal_in,
    normal_scratch,
    normal_stencil,
    value_at_world,
)

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import LatticeGeometry
    from isolume.volumes import Volume

LANDING_STEPS = 32_000
"""Steps of a landing offset per reach (`plan.landing_offsets`): int16 holds ±32 767, so an
offset of a whole reach keeps 2 % to spare for the float rounding of a clamped move."""
UNLANDED = np.iinfo(np.int16).min
"""The landing offset of a level a texel does not use (`Plan.landing`)."""
CONVERGED_FRACTION = 0.1
"""A texel reaches a level when |ρ(p) − L| ends below this fraction of the level spacing."""
NEWTON_ITERATIONS = 4
"""Newton steps onto a level (`plan.project_to_level`'s default; the reach tests')."""


def lattice_arrays(geometry: LatticeGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the kernels read of a lattice: its (3,) int64 shape (Z, Y, X) and its (3,)
    float64 world xyz lower corner and texel size."""
    return (np.asarray(geometry.shape, np.int64), np.asarray(geometry.lo, np.float64),
            np.asarray(geometry.texel_size, np.float64))


def field_arrays(volume: Volume) -> tuple[np.ndarray, ...]:
    """What the kernels read of a volume: its (Z, Y, X, 1) and (Z, Y, X) samples, 1 / (2 h)
    per axis (x, y, z), its (3,) origin and spacing (world xyz)."""
    data, _, inverse, origin, spacing = normal_stencil(volume)
    return data[..., None], data, inverse, origin, spacing


def landing_offsets(points: np.ndarray, centres: np.ndarray, reach: float) -> np.ndarray:
    """(N, 3) int16 offsets of world points (N, 3) — Newton moves of at most `reach` world
    units — from their texels' centres (N, 3), in steps of `reach` / `LANDING_STEPS`: how
    `Plan.landing` keeps them (NaN becomes `UNLANDED`)."""
    steps = (np.asarray(points, np.float64) - centres) * (LANDING_STEPS / reach)
    missing = np.isnan(steps).any(axis=1)
    codes = np.rint(np.clip(np.nan_to_num(steps), -LANDING_STEPS, LANDING_STEPS))
    codes[missing] = UNLANDED
    return codes.astype(np.int16)


def landed_points(offsets: np.ndarray, centres: np.ndarray, reach: float) -> np.ndarray:
    """(N, 3) float64 world points from `landing_offsets` (N, 3) of the same `reach` and
    the centres (N, 3); NaN where `UNLANDED`."""
    points = centres + offsets * (reach / LANDING_STEPS)
    points[offsets[:, 0] == UNLANDED] = np.nan
    return points


@dataclass(frozen=True)
class NearerLandings:
    """Where a plan's (T,) texels `ids` land on their nearer level: the (T, 2, 3) `landing`
    offsets (`Plan.landing`, in steps of `reach` / `LANDING_STEPS`) of their upper level
    where `upper` (T,) bool, else of their lower one."""

    geometry: LatticeGeometry
    ids: np.ndarray
    landing: np.ndarray
    upper: np.ndarray
    reach: float

    def points(self, at: np.ndarray) -> np.ndarray:
        """(N, 3) float64 world points of the texels at (N,) positions `at`."""
        return landed_points(np.where(self.upper[at, None], self.landing[at, 1],
                                      self.landing[at, 0]),
                             self.geometry.centres(self.ids[at]), self.reach)


def start_lift(volume: Volume, config: BakeConfig) -> float:
    """How far off its level a path starts, world units: `config.offset` voxels (of the
    mean spacing) along its lit side's normal (`baking.passes.start_points`)."""
    return config.offset * float(np.mean(volume.spacing))


@dataclass(frozen=True)
class LandedStarts:
    """What the kernels read of a bake to make points, normals and start points from the
    plan's landings (`Plan.landing`, in steps of `newton_reach`), gathered once for many
    calls (a level's chunks, a commit's facings, a level's side probes)."""

    lattice: tuple
    step: float
    lift: float
    field: tuple
    weights: np.ndarray

    @classmethod
    def of(cls, volume: Volume, geometry: LatticeGeometry, config: BakeConfig,
           reach: float) -> LandedStarts:
        """The arrays of a bake of `volume` on `geometry` whose landings are in steps of
        `reach` / `LANDING_STEPS`."""
        return cls(lattice_arrays(geometry), reach / LANDING_STEPS, start_lift(volume, config),
                   field_arrays(volume), normal_stencil(volume, config.normals == "smooth")[1])

    def points(self, ids: np.ndarray, positions: np.ndarray, upper: np.ndarray,
               landing: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`passes.start_points` of the texels at (N,) `positions` of the (T,) lattice
        `ids`, from their (T, 2, 3) `landing` offsets on their upper level where `upper`
        (N,), else their lower one, lit on the side (T,) `high` says
        (`landed_starts`, one compiled call).

        Returns:
            origins, normals: (N, 3) float32.
        """
        return landed_starts(self.lattice, ids, positions, upper, landing, self.step, high,
                             self.lift, self.field, self.weights)


@numba.njit(**PART)
def centre_of(lattice: tuple, flat: int) -> tuple[float, float, float]:
    """The world (x, y, z) centre of texel `flat` (`LatticeGeometry.centres`), compiled
    into its callers' loops (`volumes.field.PART`)."""
    shape, lo, texel_size = lattice
    layer = shape[1] * shape[2]
    k = flat // layer
    j = (flat - k * layer) // shape[2]
    i = flat - k * layer - j * shape[2]
    return (lo[0] + (i + 0.5) * texel_size[0], lo[1] + (j + 0.5) * texel_size[1],
            lo[2] + (k + 0.5) * texel_size[2])


@numba.njit(**JIT)
def gradient_norms(lattice: tuple, ids: np.ndarray, field: tuple, w: np.ndarray, h: float,
                   out: np.ndarray) -> None:
    """out (N,) = |∇ρ| × `h` at the centres of the (N,) texels `ids` (value units per `h`
    world units): ``np.linalg.norm(volumes.gradient_at(volume, centres), axis=1) * h`` —
    the gradient as float32, its float32 length times `h` in float32, as numpy computes
    it — with the stencil weights `w`."""
    _, data, inverse, origin, spacing = field
    corners = np.empty((8, 3), np.float32)
    window = np.empty((4, 4, 4), np.float32)
    g = np.empty(3)
    scale = np.float32(h)
    for r in range(len(ids)):
        cx, cy, cz = centre_of(lattice, ids[r])
        gradient_lerp(data, w, inverse, (cz - origin[2]) / spacing[2],
                      (cy - origin[1]) / spacing[1], (cx - origin[0]) / spacing[0],
                      corners, window, g)
        gx, gy, gz = np.float32(g[0]), np.float32(g[1]), np.float32(g[2])
        out[r] = np.sqrt(gx * gx + gy * gy + gz * gz) * scale


@numba.njit(**PART)
def _encode(point: np.ndarray, centre: np.ndarray, r: int, reach: float, out: np.ndarray,
            t: int) -> None:
    """out[t] (3,) int16 = `plan.landing_offsets` of the point ``point[r]`` from its
    texel's centre ``centre[r]`` ((N, 3) both)."""
    scale = LANDING_STEPS / reach
    sx = (point[r, 0] - centre[r, 0]) * scale
    sy = (point[r, 1] - centre[r, 1]) * scale
    sz = (point[r, 2] - centre[r, 2]) * scale
    if sx != sx or sy != sy or sz != sz:
        out[t, 0] = out[t, 1] = out[t, 2] = UNLANDED
    else:
        out[t, 0] = np.int16(np.rint(min(max(sx, -LANDING_STEPS), LANDING_STEPS)))
        out[t, 1] = np.int16(np.rint(min(max(sy, -LANDING_STEPS), LANDING_STEPS)))
        out[t, 2] = np.int16(np.rint(min(max(sz, -LANDING_STEPS), LANDING_STEPS)))


@numba.njit(**PART)
def landed_normal(lattice: tuple, flat: int, landing: np.ndarray, t: int, side: int,
                  step: float, field: tuple, w: np.ndarray, scratch: tuple
                  ) -> tuple[float, float, float, np.float32, np.float32, np.float32]:
    """(px, py, pz, nx, ny, nz): where texel `flat` lands — its centre moved by the (3,)
    int16 offsets ``landing[t, side]`` in steps of `step` world units (`landed_points`;
    NaN where `UNLANDED`) — and the float32 normal there towards low values (stencil
    weights `w`: `volumes.normals_at`); `scratch`: `volumes.field.normal_scratch()`.
    Compiled into its callers' loops, as `volumes.field.PART` says why."""
    _, data, inverse, origin, spacing = field
    px, py, pz = centre_of(lattice, flat)
    if landing[t, side, 0] == UNLANDED:
        px = py = pz = np.nan
    else:
        px += landing[t, side, 0] * step
        py += landing[t, side, 1] * step
        pz += landing[t, side, 2] * step
    nx, ny, nz = normal_in(data, w, inverse, origin, spacing, px, py, pz, False, scratch)
    return px, py, pz, nx, ny, nz


@numba.njit(**JIT)
def landed_starts(lattice: tuple, ids: np.ndarray, texels: np.ndarray, upper: np.ndarray,
                  landing: np.ndarray, step: float, high: np.ndarray, lift: float,
                  field: tuple, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start points and normals of the (N,) plan positions `texels` (`passes.start_points`
    at their landings).

    Args:
        ids: (T,) flat lattice ids of the plan's texels; texels: (N,) positions into them.
        upper: (N,) bool, the level is the texel's upper one (its landing's side).
        landing: (T, 2, 3) int16 `Plan.landing` offsets, in units of `step` world units.
        high: (T,) bool `Plan.high`; lift: the start point's offset off the surface,
            world units (`start_lift`).
        w: the weights of the normals' stencil (the bake's).

    Returns:
        origins (N, 3) and normals (N, 3) float32 (NaN where a texel has no landing).
    """
    n = len(texels)
    origins = np.empty((n, 3), np.float32)
    normals = np.empty((n, 3), np.float32)
    scratch = normal_scratch()
    unit = np.empty(3, np.float32)
    point = np.empty(3)
    for r in range(n):
        t = texels[r]
        point[0], point[1], point[2], unit[0], unit[1], unit[2] = landed_normal(
            lattice, ids[t], landing, t, 1 if upper[r] else 0, step, field, w, scratch)
        for a in range(3):
            normal = -np.float64(unit[a]) if high[t] else np.float64(unit[a])
            origins[r, a] = np.float32(point[a] + lift * normal)
            normals[r, a] = np.float32(normal)
    return origins, normals


@numba.njit(**JIT)
def reach_tests(lattice: tuple, ids: np.ndarray, lower: np.ndarray, levels: np.ndarray,
                side: int, high: np.ndarray, which: np.ndarray, landing: np.ndarray,
                ok: np.ndarray, moved: np.ndarray, reach: float, lift: float, field: tuple,
                newton_w: np.ndarray, lift_w: np.ndarray, scratch: np.ndarray, first: int,
                stop: int) -> None:
    """The reach tests (`plan._Reaches`) of the texels first … stop − 1 where `which`
    (T,) bool: each is moved from its centre onto its lower (`side` 0) or upper (1) level
    — its landing in `landing` (T, 3) int16 (that side's `Plan.landing`), projected here
    where it has none (`_project_unlanded`) — and ``ok`` (T,) is set where it lands
    within `CONVERGED_FRACTION` of its level spacing of the level (`_level_checks`) and,
    when `lift` > 0, the point `lift` world units along its lit side's normal (`high`
    (T,): the high side) lies on that side (`_lit_side_checks`: its paths start outside
    the level); ``moved`` (T,) gets the move's length, world units.

    Args:
        ids, lower: (T,) flat lattice ids and lower level indices; levels: (K,) isovalues.
        newton_w, lift_w: the stencil weights of Newton's gradient (smoothed) and of the
            lit side's normal (the bake's).
        scratch: (1,) of `volumes.value_at`'s result type.
    """
    _project_unlanded(lattice, ids, lower, levels, side, which, landing, reach, field,
                      newton_w, first, stop)
    landed = np.empty((stop - first, 3))
    lifted = _level_checks(lattice, ids, lower, levels, side, which, landing, ok, moved,
                           reach, lift, field, scratch, first, stop, landed)
    if len(lifted):
        _lit_side_checks(lower, levels, side, high, ok, lifted, landed, lift, field, lift_w,
                         first)


@numba.njit(**JIT)
def _project_unlanded(lattice: tuple, ids: np.ndarray, lower: np.ndarray,
                      levels: np.ndarray, side: int, which: np.ndarray, landing: np.ndarray,
                      reach: float, field: tuple, w: np.ndarray, first: int,
                      stop: int) -> None:
    """The texels first … stop − 1 where `which` without a landing yet, moved from their
    centres onto their level by `NEWTON_ITERATIONS` Newton steps (stencil weights `w`, at
    most `reach` world units) in one call, their landings written into `landing`."""
    todo = np.empty(stop - first, np.int64)
    n = 0
    for t in range(first, stop):
        if which[t] and landing[t, 0] == UNLANDED:
            todo[n] = t
            n += 1
    if n == 0:
        return
    cube, data, inverse, origin, spacing = field
    starts = np.empty((n, 3))
    targets = np.empty(n)
    for r in range(n):
        starts[r, 0], starts[r, 1], starts[r, 2] = centre_of(lattice, ids[todo[r]])
        targets[r] = levels[lower[todo[r]] + side]
    projected = np.empty((n, 3))
    newton_steps(cube, data, w, inverse, origin, spacing, starts, targets, reach,
                 NEWTON_ITERATIONS, projected)
    for r in range(n):
        _encode(projected, starts, r, reach, landing, todo[r])


@numba.njit(**JIT)
def _level_checks(lattice: tuple, ids: np.ndarray, lower: np.ndarray, levels: np.ndarray,
                  side: int, which: np.ndarray, landing: np.ndarray, ok: np.ndarray,
                  moved: np.ndarray, reach: float, lift: float, field: tuple,
                  scratch: np.ndarray, first: int, stop: int, landed: np.ndarray
                  ) -> np.ndarray:
    """Each texel first … stop − 1 where `which`: its landing point into `landed` (row
    t − first), ``ok`` where the field there is within the tolerance of its level, its
    move's length into `moved`. Returns the texels whose lit side is to be checked (ok,
    with a `lift`)."""
    cube, _, _, origin, spacing = field
    lifted = np.empty(stop - first, np.int64)
    m = 0
    for t in range(first, stop):
        if not which[t]:
            continue
        cx, cy, cz = centre_of(lattice, ids[t])
        x = y = z = np.nan
        if landing[t, 0] != UNLANDED:
            x = cx + landing[t, 0] * (reach / LANDING_STEPS)
            y = cy + landing[t, 1] * (reach / LANDING_STEPS)
            z = cz + landing[t, 2] * (reach / LANDING_STEPS)
        landed[t - first, 0], landed[t - first, 1], landed[t - first, 2] = x, y, z
        tol = CONVERGED_FRACTION * (levels[lower[t] + 1] - levels[lower[t]])
        ok[t] = (x == x and y == y and z == z and abs(
            value_at_world(cube, origin, spacing, x, y, z, scratch)
            - levels[lower[t] + side]) <= tol)
        if ok[t] and lift > 0:
            lifted[m] = t
            m += 1
        dx, dy, dz = x - cx, y - cy, z - cz
        moved[t] = np.sqrt(dx * dx + dy * dy + dz * dz)
    return lifted[:m]


@numba.njit(**JIT)
def _lit_side_checks(lower: np.ndarray, levels: np.ndarray, side: int, high: np.ndarray,
                     ok: np.ndarray, lifted: np.ndarray, landed: np.ndarray, lift: float,
                     field: tuple, w: np.ndarray, first: int) -> None:
    """``ok`` of the texels `lifted`: does the point `lift` world units from its landing
    (`landed` row t − `first`) along the normal of its lit side (stencil weights `w`) lie
    on that side of its level? One call of `volumes.field.along_normals` a side."""
    cube, data, inverse, origin, spacing = field
    for flip in (False, True):
        rows = lifted[high[lifted] == flip]
        if len(rows) == 0:
            continue
        points = np.empty((len(rows), 3))
        for r in range(len(rows)):
            for a in range(3):
                points[r, a] = landed[rows[r] - first, a]
        beyond = np.empty(len(rows))
        along_normals(cube, data, w, inverse, origin, spacing, points, lift,
                      1.0 if flip else -1.0, beyond)
        for r in range(len(rows)):
            level = levels[lower[rows[r]] + side]
            ok[rows[r]] = beyond[r] - level > 0 if flip else beyond[r] - level < 0
