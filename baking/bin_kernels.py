"""Compiled loops of the counting sorts by bin (`plan.grouped_by_bin`: the level choice's
percentiles, the nearest points of a view) and of the nearest points themselves
(`preview.nearest_points`): a texel's trilinear corners, and the nearest of a bin's
points to each texel it holds."""

from __future__ import annotations

import numba
import numpy as np

from isolume.baking.kernels import lower_corner
from isolume.volumes.field import JIT


@numba.njit(**JIT)
def count_bins(which: np.ndarray, shift: int, lo: int, hi: int, counts: np.ndarray
               ) -> None:
    """Into (B,) `counts`: how many of ``which[lo:hi] >> shift`` (bin indices < B) fall in
    each bin."""
    for i in range(lo, hi):
        counts[which[i] >> shift] += 1


@numba.njit(**JIT)
def scatter_by_bin(which: np.ndarray, shift: int, values: np.ndarray, lo: int, hi: int,
                   places: np.ndarray, out: np.ndarray) -> None:
    """Put ``values[lo:hi]`` into `out`, each at its bin's (``which[i] >> shift``) next
    place (`places`, (B,), moved on as they fill): with each block's places where the
    blocks before it end in each bin, the blocks together make
    ``values[np.argsort(which >> shift, kind="stable")]``."""
    for i in range(lo, hi):
        b = which[i] >> shift
        out[places[b]] = values[i]
        places[b] += 1


@numba.njit(**JIT)
def scatter_index_by_bin(which: np.ndarray, shift: int, lo: int, hi: int,
                         places: np.ndarray, out: np.ndarray) -> None:
    """`scatter_by_bin` of the indices themselves (values ``arange(len(which))``)."""
    for i in range(lo, hi):
        b = which[i] >> shift
        out[places[b]] = i
        places[b] += 1


@numba.njit(**JIT)
def corner_reads(coords: np.ndarray, shape: np.ndarray, size: np.ndarray, scale: float,
                 lo: int, hi: int, read: np.ndarray, close: np.ndarray) -> None:
    """For the points ``coords[lo:hi]`` ((N, 3) float64 texel coordinates z, y, x in a grid
    of (3,) int64 `shape`): into ``read[8 i + k]`` (int64) the flat id of the corner k
    (bit 2: z, bit 1: y, bit 0: x) that a trilinear lookup at point i reads, as
    `lattice.trilinear_corners` gives them, and into ``close[8 i + k]`` (float64) the
    squared distance from the point to that corner's centre, each axis scaled by (3,)
    `size` (world units per texel, z, y, x), over `scale`."""
    nz, ny, nx = shape[0], shape[1], shape[2]
    for i in range(lo, hi):
        cz, cy, cx = coords[i, 0], coords[i, 1], coords[i, 2]
        z0, y0, x0 = lower_corner(cz, nz), lower_corner(cy, ny), lower_corner(cx, nx)
        for k in range(8):
            z = min(z0 + (k >> 2 & 1), nz - 1)
            y = min(y0 + (k >> 1 & 1), ny - 1)
            x = min(x0 + (k & 1), nx - 1)
            dz, dy, dx = (z - cz) * size[0], (y - cy) * size[1], (x - cx) * size[2]
            read[8 * i + k] = (z * ny + y) * nx + x
            close[8 * i + k] = (dz * dz + dy * dy + dx * dx) / scale


@numba.njit(**JIT)
def nearest_in_bins(read: np.ndarray, close: np.ndarray, entries: np.ndarray,
                    starts: np.ndarray, b0: int, b1: int, bits: int, texel: np.ndarray,
                    point: np.ndarray, held_in: np.ndarray) -> None:
    """The nearest entry of each texel, bins [`b0`, `b1`) of `entries`.

    (E,) int64 `entries` holds indices into (E,) int64 `read` (texel ids) and (E,) float64
    `close` (their closeness), grouped by bin ``read >> bits`` (bin b:
    ``entries[starts[b]:starts[b + 1]]``, (B + 1,) int64 `starts`), each bin in ascending
    order. For every texel of a bin, ascending, the bin's first slots of the (E,) int64
    outputs get its id (`texel`) and its entry with the least closeness, over 8
    (`point`: the first such entry on ties; a NaN closeness loses to any number): what
    sorting the entries by texel, then closeness, stably, and keeping each texel's first
    would give. (B,) int64 `held_in` gets each bin's count of texels. A bin's entries are
    all read before its slots are written: `texel` may be `entries` itself.
    """
    slots = 1 << bits
    best = np.full(slots, -1, np.int64)
    touched = np.empty(slots, np.int64)
    for b in range(b0, b1):
        held = 0
        for k in range(starts[b], starts[b + 1]):
            j = entries[k]
            slot = read[j] & (slots - 1)
            now = best[slot]
            if now < 0:
                best[slot] = j
                touched[held] = slot
                held += 1
            elif close[j] < close[now] or (close[now] != close[now] and close[j] == close[j]):
                best[slot] = j
        ordered = np.sort(touched[:held])
        for q in range(held):
            j = best[ordered[q]]
            texel[starts[b] + q] = read[j]
            point[starts[b] + q] = j // 8
            best[ordered[q]] = -1
        held_in[b] = held


@numba.njit(**JIT)
def gather_bins(texel: np.ndarray, point: np.ndarray, starts: np.ndarray,
                held_in: np.ndarray, places: np.ndarray, b0: int, b1: int,
                texel_out: np.ndarray, point_out: np.ndarray) -> None:
    """Bins [`b0`, `b1`) of `nearest_in_bins`' outputs packed: the first ``held_in[b]``
    slots of bin b (from ``starts[b]``) of (E,) `texel` and `point` copied to
    ``places[b]`` on of `texel_out` and `point_out`."""
    for b in range(b0, b1):
        for q in range(held_in[b]):
            texel_out[places[b] + q] = texel[starts[b] + q]
            point_out[places[b] + q] = point[starts[b] + q]
