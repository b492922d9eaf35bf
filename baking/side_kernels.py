"""A level's side probes in one compiled call per work item (`baking.sides`): each
texel's point on its nearer level and its normal there, the probe origins of each side,
the on-side and box-reach tests (`volumes.reach.may_open_at`), their rays, Embree called
per ray (`embree_kernels.occluded_one`), the open counts and the side rule — with no
Python, and so no wait for the GIL, between
them. The same sides as the array code `baking.sides` runs where a scene has no
compiled calls (`trace.EmbreeCalls`): `sides.open_rays`, `sides.side_rule`,
`sides.parity`. A texel's rays stop once the rule's choice is settled (`enough_open`):
its counts can then be lower than the array code's, never its side.
"""

from __future__ import annotations

import numba
import numpy as np

from isolume.baking.embree_kernels import occluded_one, ray_buffer
from isolume.baking.kernels import path_starts
from isolume.baking.plan_kernels import landed_normal
from isolume.volumes.field import JIT, PART, normal_scratch, value_at_world
from isolume.volumes.reach import may_open_at


@numba.njit(**JIT)
def open_counts(calls: tuple[int, ...], key: np.uint32, ids: np.ndarray, points: np.ndarray,
                normals: np.ndarray, offset: float, sign: float, which: np.ndarray,
                cube: np.ndarray, origin: np.ndarray, spacing: np.ndarray,
                level: float, scratch: np.ndarray, first: int, probes: int,
                reach: tuple, enough: np.ndarray, settle: bool) -> np.ndarray:
    """(N,) int64: how many of `probes` rays from each point where `which` (N,) bool meet
    nothing, counted until `enough` (N,) of them have (later rays are not traced) or, with
    `settle`, until some have and the rays left could not make it `enough`; 0 elsewhere,
    where the probes' origin does not lie on their side, and where `reach` proves that
    side closed (`volumes.reach.may_open_at`; ``reach[0]``: False for no such test, then
    its arrays, direction and frame). With `enough` of `probes` and no `settle`, every
    ray is counted.

    Args:
        calls: the level scene's `trace.EmbreeCalls`; key: the probes' seed key.
        ids: (N,) int64 flat lattice ids (the paths' keys: samples `first` … `first` +
            `probes` − 1).
        points: (N, 3) float64 world points on the level; normals: (N, 3) float64 unit
            normals towards low values.
        offset, sign: the origins are ``points + sign · offset · normals`` (world units),
            the rays cosine-distributed about ``sign · normals``; ``sign`` > 0: the low
            side, whose origins must have values below `level`, else above.
        cube: the volume's (Z, Y, X, 1) samples; origin, spacing: (3,) float64, world xyz.
        level: the isovalue in `scratch`'s type, (1,) that of `volumes.value_at`.
    """
    tested, grid, steps, up, frame = reach
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
            if ((beyond < 0) if sign > 0 else (beyond > 0)) and (
                    not tested or may_open_at(grid, steps, up, frame, x, y, z, level)):
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
            samples[r * probes + s] = first + s
    _, o, _, d = path_starts(key, picked, pos, samples, texels, starts, dirs)
    ray, bits, address = ray_buffer()
    for r in range(m):
        need = enough[rows[r]]
        count = 0
        for s in range(probes):
            if settled_count(count, probes - s, need, settle):
                break
            j = r * probes + s
            count += not occluded_one(calls, ray, bits, address, o[0, j], o[1, j], o[2, j],
                                      d[0, j], d[1, j], d[2, j])
        out[rows[r]] = count
    return out


@numba.njit(**PART)
def settled_count(opened: int, left: int, enough: int, settle: bool) -> bool:
    """Whether a side's count of `opened` rays, `left` more to trace, is settled (`open_counts`):
    `enough` of them open, or, with `settle`, some open and the rays left could not make it
    `enough`."""
    return opened >= enough or (settle and opened > 0 and opened + left < enough)


@numba.njit(**JIT)
def enough_other(probes: int, clearly_more: float) -> int:
    """Open rays of a texel's other side that settle its side (`sides.side_rule`): past
    `probes` / `clearly_more`, no count of the default side's rays lights it alone."""
    return int(probes // clearly_more) + 1 if clearly_more > 0 else 1


@numba.njit(**JIT)
def enough_open(other: np.ndarray, probes: int, rays: int, clearly_more: float) -> np.ndarray:
    """(N,) int64: the open rays of its default side that settle a texel's side, given the
    (N,) open `other` rays of its other side and `rays` on the default side
    (`sides.side_rule`): the fewest m ≥ 1 with m · `probes` ≥ `clearly_more` · other ·
    `rays` (lit on the default side alone), `rays` + 1 where no count reaches that (one
    open ray settles it: both sides lit)."""
    out = np.empty(len(other), np.int64)
    for i in range(len(other)):
        m = 1
        while m <= rays and m * probes < clearly_more * other[i] * rays:
            m += 1
        out[i] = m
    return out


@numba.njit(**JIT)
def probe_sides(calls: tuple[int, ...], key: np.uint32, lattice: tuple, ids: np.ndarray,
                at: np.ndarray, upper: np.ndarray, landing: np.ndarray, step: float,
                field: tuple, w: np.ndarray, offset: float, level: float,
                scratch: np.ndarray, probes: int, confirm: int, default: bool,
                clearly_more: float, reach: tuple, high: np.ndarray) -> None:
    """`sides.open_rays` and `sides.side_rule` of the texels at plan positions `at` (N,)
    into ``high[at]``, in one call: each texel's point on its nearer level (its `landing`
    (T, 2, 3) offsets, in steps of `step` world units, of its upper level where `upper`
    (T,), else its lower one; `plan_kernels.NearerLandings`), its normal there (stencil
    weights `w`: `volumes.normals_at`), the open probe rays of the side other than the
    `default` one, then of the default side where that one is open, and `confirm` more
    where none of those left (`open_counts`; each side's rays only until its count settles
    the rule: `enough_other`, `enough_open`), and the rule with the texel's checkerboard
    parity.

    Args:
        lattice, field: `plan_kernels.lattice_arrays`, `plan_kernels.field_arrays`.
        ids: (T,) int32 or int64 flat lattice ids of the plan's texels (the probes' keys,
            the parity).
        offset, level, scratch, probes: as `open_counts`'s; confirm:
            `sides.CONFIRM_PROBES`; clearly_more: `sides.CLEARLY_MORE`.
        reach: as `open_counts`'s, for the side other than the default one (its probes
            are not traced where it proves that side closed).
    """
    cube, _, _, origin, spacing = field
    n = len(at)
    points = np.empty((n, 3))
    normals = np.empty((n, 3))
    picked = np.empty(n, np.int64)
    unit = np.empty(3, np.float32)
    normal = normal_scratch()
    for r in range(n):
        t = at[r]
        picked[r] = ids[t]
        points[r, 0], points[r, 1], points[r, 2], unit[0], unit[1], unit[2] = landed_normal(
            lattice, ids[t], landing, t, 1 if upper[t] else 0, step, field, w, normal)
        for a in range(3):
            normals[r, a] = np.float64(unit[a])
    other_sign = 1.0 if default else -1.0  # the low side's normal is +normals
    settled = np.full(n, enough_other(probes, clearly_more), np.int64)
    other = open_counts(calls, key, picked, points, normals, offset, other_sign,
                        np.ones(n, np.bool_), cube, origin, spacing, level, scratch, 0, probes,
                        reach, settled, False)
    untested = (False, reach[1], reach[2], reach[3], reach[4])
    mine = open_counts(calls, key, picked, points, normals, offset, -other_sign, other > 0,
                       cube, origin, spacing, level, scratch, 0, probes, untested,
                       enough_open(other, probes, probes, clearly_more), True)
    confirmed = (other > 0) & (mine == 0)
    mine += open_counts(calls, key, picked, points, normals, offset, -other_sign, confirmed,
                        cube, origin, spacing, level, scratch, probes, confirm, untested,
                        enough_open(other, probes, probes + confirm, clearly_more), True)
    shape = lattice[0]
    for r in range(n):
        flat = picked[r]
        odd = (flat // (shape[1] * shape[2]) + flat // shape[2] % shape[1]
               + flat % shape[2]) & 1 == 1
        if mine[r] > 0 and other[r] > 0:  # the default side alone where clearly more open
            rays = probes + confirm if confirmed[r] else probes
            lit = default if mine[r] * probes >= clearly_more * other[r] * rays else odd
        elif other[r] > 0:
            lit = not default
        else:
            lit = default
        high[at[r]] = lit
