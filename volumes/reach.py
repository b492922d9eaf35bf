"""Which parts of a volume connect to the faces of its box, level by level.

A ray leaves the box on the high-value side of a level ρ = L only through values above L
all along it: where the region ρ > L around a point touches none of the box's faces, no
camera outside the box sees the high side of the level there, and no probe ray need ask.
`BoxReach` holds, for every voxel, the highest level at which it connects to the box's
faces through values at or above that level (the largest, over chains of 26-neighbours
from a voxel on a face, of the chain's least value) — or, looking down, the lowest level
at which it connects through values at or below it.

Chains of 26-neighbours over-connect the trilinear field, never under-connect it: a point
of a cell above L has a corner above L (the trilinear value is a mean of the corners),
the eight corners of a cell are 26-neighbours of one another, and a path from one cell
into the next crosses a face, edge or corner of both whose value above L makes one of
their shared corners above L. So "no corner of the point's cell reaches L" proves the side
closed; the converse only says a ray may leave. Marching cubes' ambiguous faces join
diagonal corners at most, which 26-neighbours join too.

The flood goes from the faces inwards, best level first, through a bucket queue over the
volume's values: the values themselves for integer samples spanning at most `EXACT_SPAN`,
else `LEVELS` levels, each value rounded up for the upward reach and down for the
downward one, so that the test errs towards "may leave". One pass over the voxels and
their 26 neighbours, on one core: 1.4 s for the 256³ foot CT, 17.6 s for it at 512³,
which the baker floods on a pool thread beside the plan's Newton steps
(`baking.sides.BoxReachAhead`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numba
import numpy as np

from isolume.volumes.core import Volume
from isolume.volumes.field import JIT, PART

LEVELS = 4096
"""Levels of the flood for float samples, or integers spanning more than `EXACT_SPAN`."""
EXACT_SPAN = 1 << 16
"""Integer samples spanning at most this many values flood on the values themselves."""
FLOOD_POPS = 1 << 22
"""Voxels a flood takes off its queue between two looks at its `stop` (0.35–0.55 s of a
core here, on the 256³ and 512³ foot: a flood on a pool thread ends soon after the plan
that asked for it is interrupted)."""


class FloodStopped(RuntimeError):
    """A `BoxReach.of` flood stopped before it was done (its `stop` set)."""


@dataclass(frozen=True)
class BoxReach:
    """How far each voxel connects to the box's faces, as indices into `levels`.

    Attributes:
        reach: (Z, Y, X) level indices (uint8 or uint16): the highest level each voxel
            reaches the faces through values at or above it (`up`), else the lowest
            through values at or below it.
        levels: (B,) float64, increasing: the values the indices stand for.
        up: which way `reach` looks.
    """

    reach: np.ndarray
    levels: np.ndarray
    up: bool

    @classmethod
    def of(cls, volume: Volume, up: bool, stop: threading.Event | None = None) -> BoxReach:
        """Flood `volume` from its box's faces, through values above a level where `up`,
        else below it, `FLOOD_POPS` voxels at a time; raises `FloodStopped` between two
        such runs once `stop` is set (the one who asked for it has gone)."""
        levels, rank = _ranked(volume.data, up)
        links = np.int32 if rank.size < np.iinfo(np.int32).max else np.int64
        after = np.full(rank.size, -2, links)
        head = np.full(len(levels), -1, np.int64)
        _seed_faces(rank, head, after)
        out = np.empty(rank.shape, rank.dtype)
        at = np.zeros(1, np.int64)
        while not _drain(rank, up, head, after, out, at, FLOOD_POPS):
            if stop is not None and stop.is_set():
                raise FloodStopped(f"{volume.name}: the flood from its box's faces stopped")
        return cls(out, levels, up)

    def arrays(self, volume: Volume) -> tuple[np.ndarray, np.ndarray, bool, np.ndarray]:
        """(`reach`, `levels`, `up`, frame) for `may_open_at` in compiled callers; frame:
        (6,) float64 `volume`'s origin and spacing, x, y, z."""
        frame = np.concatenate([np.asarray(volume.origin, np.float64),
                                np.asarray(volume.spacing, np.float64)])
        return self.reach, self.levels, self.up, frame

    def may_open(self, volume: Volume, points: np.ndarray, level: float) -> np.ndarray:
        """(N,) bool: may a ray from each of the (N, 3) world `points` leave the
        box of `volume` (the one flooded) on the side of the level ρ = `level` this reach
        looks to? False proves it cannot."""
        out = np.empty(len(points), bool)
        _may_open(*self.arrays(volume), np.ascontiguousarray(points, np.float64),
                  float(level), out)
        return out


def _ranked(data: np.ndarray, up: bool) -> tuple[np.ndarray, np.ndarray]:
    """The flood's levels (B,) float64 and the (Z, Y, X) level index of each sample,
    rounded up where `up`, else down."""
    low, high = data.min(), data.max()
    if data.dtype.kind in "iu" and int(high) - int(low) < EXACT_SPAN:
        levels = np.arange(int(low), int(high) + 1, dtype=np.float64)
        kind = np.uint8 if len(levels) <= 256 else np.uint16
        if data.dtype == kind and int(low) == 0:
            return levels, data
        return levels, (data.astype(np.int32) - int(low)).astype(kind)
    levels = np.linspace(float(low), float(high), LEVELS)
    levels[-1] = float(high)
    if up:
        return levels, np.searchsorted(levels, data, side="left").astype(np.uint16)
    return levels, (np.searchsorted(levels, data, side="right") - 1).astype(np.uint16)


@numba.njit(**JIT)
def _seed_faces(rank: np.ndarray, head: np.ndarray, after: np.ndarray) -> None:
    """Queue the voxels on the box's faces, each in the bucket of its own level index in
    the (Z, Y, X) `rank`: `head` (B,) the buckets' first voxels, all −1, and `after`
    (N,) the queue's links, all −2 (−2: not queued), both updated."""
    nz, ny, nx = rank.shape
    flat = rank.reshape(-1)
    for z in range(nz):
        for y in range(ny):
            inner = 0 < z < nz - 1 and 0 < y < ny - 1
            step = max(nx - 1, 1) if inner else 1
            for x in range(0, nx, step):
                i = (z * ny + y) * nx + x
                b = flat[i]
                after[i], head[b] = head[b], i


@numba.njit(**JIT)
def _drain(rank: np.ndarray, up: bool, head: np.ndarray, after: np.ndarray,
           out: np.ndarray, at: np.ndarray, pops: int) -> bool:
    """Go on with the flood of the (Z, Y, X) level indices `rank` (`_seed_faces` began
    it): take at most `pops` voxels off the bucket queue `head`, `after`, best level
    first from bucket step `at[0]` (updated), into `out` (Z, Y, X) the level index at
    which each connects to the box's faces through 26-neighbours at or above it (`up`),
    else at or below it. Returns whether the queue is empty (the flood done). A neighbour
    first met from a voxel at level b gets min(b, its own) (max where not `up`), which no
    later voxel betters, so each voxel is queued once, and the result is the same
    whatever the order within a bucket and however the flood is cut into calls."""
    nz, ny, nx = rank.shape
    flat, into = rank.reshape(-1), out.reshape(-1)
    count = head.size
    left = pops
    while at[0] < count:
        b = count - 1 - at[0] if up else at[0]
        while head[b] >= 0:
            if left == 0:
                return False
            left -= 1
            i = head[b]
            head[b] = after[i]
            into[i] = b
            z, rest = divmod(i, ny * nx)
            y, x = divmod(rest, nx)
            for k in range(max(z - 1, 0), min(z + 2, nz)):
                for j in range(max(y - 1, 0), min(y + 2, ny)):
                    for m in range(max(x - 1, 0), min(x + 2, nx)):
                        n = (k * ny + j) * nx + m
                        if after[n] == -2:
                            c = min(b, flat[n]) if up else max(b, flat[n])
                            after[n], head[c] = head[c], n
        at[0] += 1
    return True


@numba.njit(**JIT)
def _may_open(reach: np.ndarray, levels: np.ndarray, up: bool, frame: np.ndarray,
              points: np.ndarray, level: float, out: np.ndarray) -> None:
    """`BoxReach.may_open` of the (N, 3) `points` into `out` (N,); `frame`: (6,) the
    volume's origin and spacing, x, y, z."""
    for i in range(len(points)):
        out[i] = may_open_at(reach, levels, up, frame, points[i, 0], points[i, 1],
                             points[i, 2], level)


@numba.njit(**PART)
def may_open_at(reach: np.ndarray, levels: np.ndarray, up: bool, frame: np.ndarray,
                x: float, y: float, z: float, level: float) -> bool:
    """Does some corner of the cell holding world (x, y, z) (clamped into the box, as
    `volumes.field.value_in` clamps) reach the box's faces at `level` — at or above it
    where `up`, else at or below it? `frame`: (6,) the volume's origin and spacing. True
    at NaN coordinates (nothing proven). One return, and no early one from the loops:
    inlined into a caller's per-point loop, it then keeps no reference counting there."""
    nz, ny, nx = reach.shape
    z0 = _lower_corner((z - frame[2]) / frame[5], nz)
    y0 = _lower_corner((y - frame[1]) / frame[4], ny)
    x0 = _lower_corner((x - frame[0]) / frame[3], nx)
    best = -np.inf if up else np.inf
    for k in range(z0, min(z0 + 2, nz)):
        for j in range(y0, min(y0 + 2, ny)):
            for m in range(x0, min(x0 + 2, nx)):
                value = levels[reach[k, j, m]]
                best = max(best, value) if up else min(best, value)
    unknown = x != x or y != y or z != z
    return unknown or ((best >= level) if up else (best <= level))


@numba.njit(**PART)
def _lower_corner(c: float, n: int) -> int:
    """Lower corner index of fractional index `c` on an axis of `n` samples, clamped (0
    for NaN)."""
    c = min(max(c, 0.0), n - 1.0) if c == c else 0.0
    return min(int(c), max(n - 2, 0))
