"""Paths where a picture's noise is: the texels of one view (`app.render.view_gi`) traced
with a budget of paths placed by what each texel's noise does to the picture.

A pixel shows the trilinear mix of eight texels. With nᵢ paths at texel i, whose paths'
luminance spreads by σᵢ (standard deviation), the squared error summed over the picture's
pixels is Σᵢ aᵢ σᵢ² / nᵢ, where aᵢ, the texel's *share* of the picture, sums the squares
of its trilinear weights over the pixels that read it (`picture_share`). For a budget of
N = Σᵢ nᵢ paths that is least at nᵢ ∝ σᵢ √aᵢ (a Lagrange multiplier), where it comes to
(Σᵢ √aᵢ σᵢ)² / N — against Σᵢ aᵢ σᵢ² · K / N for the same paths spread evenly over the
K texels. Open sky and flat faces spread little; a fold beside a contact, a pocket that
sees the sky through a narrow opening, spread much.

So every texel first gets `PILOT` paths; its spread is estimated from them and averaged
over its 27-neighbourhood among the view's texels (`neighbour_mean`: a few paths give a
noisy spread, one whose paths agreed by chance — all blocked — none at all, while the
light's spread changes gently across a surface); the rest of the budget goes out in
proportion to that spread times √aᵢ (`allocate`), at least the pilot and at most `CAP`
times the budget at a texel. Under a sky from every direction, a texel whose paths all
stayed dark then goes on to `baking.lattice.TRAPPED_PATHS`: below that a display would
draw it black, at it the texel is known to be trapped and left out of the lookups (a
pass of that many paths everywhere gets this for free).

A texel's paths are the same as a pass of even paths would trace (sample s of texel t,
the same keys, and with `Tracing.stratified` the same point of the texel's stratified
sequence: its first n samples are the sequence's first n, however they were split into
passes), traced in sample order within one work item (`trace_counts`), so the picture is
the same bits for any number of threads. Measured on the 58 render cases of
``../shared/data`` (docs/accuracy.md, "The traced light of one picture"): 32 independent
paths a texel on average placed so are as accurate as 64 at every texel, and 28 with
stratified first directions more accurate than 32 independent ones in every case.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numba
import numpy as np

from isolume.baking.kernels import lower_corner
from isolume.baking.lattice import LUMINANCE
from isolume.baking.passes import PassSums, PathStarts, Tracing, chunk_bounds, trace_chunk
from isolume.volumes import cores
from isolume.volumes.field import JIT

if TYPE_CHECKING:
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.trace import Scene

PILOT = 8
"""Paths every texel gets before the rest of the budget is placed (at most the budget)."""
CAP = 8
"""The most paths a texel gets, in units of the budget per texel (a spread misjudged high
costs at most this)."""
BLOCK = 1 << 15
"""Texels one work item of `neighbour_mean` takes, at most."""


def picture_share(geometry: LatticeGeometry, texels: np.ndarray, points: np.ndarray
                  ) -> np.ndarray:
    """(K,) float64: for each of the (K,) sorted flat lattice ids `texels`, the sum over
    the (N, 3) world `points` (a picture's visible surface, one per pixel) of the square
    of its weight in their trilinear lookups (`baking.lattice.trilinear_corners`; 0 for a
    texel none reads)."""
    share = np.zeros(len(texels))
    if len(texels) and len(points):
        _shares(np.ascontiguousarray(geometry.to_texel_coords(points), np.float64),
                np.array(geometry.shape, np.int64), np.ascontiguousarray(texels, np.int64),
                share)
    return share


@numba.njit(**JIT)
def _shares(coords: np.ndarray, shape: np.ndarray, texels: np.ndarray, share: np.ndarray
            ) -> None:
    """Add to ``share`` (K,) the squared trilinear weights of the (N, 3) z, y, x texel
    `coords` at the (K,) sorted flat ids `texels` of a box of (3,) `shape`, corners and
    weights as `baking.lattice.trilinear_corners` makes them (`kernels.lower_corner`); a
    point with a NaN coordinate reads nothing."""
    base = np.empty(3, np.int64)
    frac = np.empty(3)
    for i in range(len(coords)):
        if coords[i, 0] != coords[i, 0] or coords[i, 1] != coords[i, 1] \
                or coords[i, 2] != coords[i, 2]:
            continue
        for a in range(3):
            base[a] = lower_corner(coords[i, a], shape[a])
            frac[a] = min(max(coords[i, a], 0.0), shape[a] - 1.0) - base[a]
        for k in range(8):
            flat = 0
            weight = 1.0
            for a in range(3):
                step = (k >> (2 - a)) & 1
                flat = flat * shape[a] + min(base[a] + step, shape[a] - 1)
                weight *= frac[a] if step else 1.0 - frac[a]
            row = np.searchsorted(texels, flat)
            if row < len(texels) and texels[row] == flat:
                share[row] += weight * weight


@numba.njit(**JIT)
def _neighbour_means(texels: np.ndarray, values: np.ndarray, shape: np.ndarray,
                     lo: int, hi: int, out: np.ndarray) -> None:
    """``out[i]`` for i in lo … hi − 1: the mean of `values` over the texels of the (K,)
    sorted flat ids `texels` in the 3 × 3 × 3 block around texel i (itself included) in a
    box of (3,) `shape` (z, y, x): per row of the block, one search for its first texel
    and a scan along x."""
    layer = shape[1] * shape[2]
    for i in range(lo, hi):
        flat = texels[i]
        z, y, x = flat // layer, flat // shape[2] % shape[1], flat % shape[2]
        total = 0.0
        count = 0
        for k in range(max(z - 1, 0), min(z + 2, shape[0])):
            for j in range(max(y - 1, 0), min(y + 2, shape[1])):
                row = (k * shape[1] + j) * shape[2]
                last = row + min(x + 1, shape[2] - 1)
                at = np.searchsorted(texels, row + max(x - 1, 0))
                while at < len(texels) and texels[at] <= last:
                    total += values[at]
                    count += 1
                    at += 1
        out[i] = total / count


def neighbour_mean(shape: tuple[int, int, int], texels: np.ndarray, values: np.ndarray
                   ) -> np.ndarray:
    """(K,) the mean of (K,) `values` over each texel's 27-neighbourhood among the (K,)
    sorted flat ids `texels` of a (Z, Y, X) lattice (itself included), in blocks on
    every core."""
    out = np.empty(len(texels))
    ids = np.ascontiguousarray(texels, np.int64)
    values = np.ascontiguousarray(values, np.float64)
    box = np.array(shape, np.int64)
    cores.for_blocks(lambda part: _neighbour_means(ids, values, box, part.start, part.stop,
                                                   out), len(texels), BLOCK, "texels")
    return out


def allocate(weight: np.ndarray, budget: int, least: int, most: int) -> np.ndarray:
    """(K,) int64 paths per texel: ⌊c · weightᵢ⌋ clamped to `least` … `most`, with the
    largest c (found by bisection between the c at which the heaviest texel leaves
    `least` and the c at which the lightest reaches `most`, on a log scale: the same bits
    on any machine) for which they sum to at most `budget` (at least K · `least`: every
    texel keeps its least). A texel of weight 0 keeps `least`."""
    weight = np.asarray(weight, np.float64)
    positive = weight[weight > 0]
    if len(positive) == 0:
        return np.full(len(weight), least, np.int64)

    def counts(c: float) -> np.ndarray:
        return np.clip(np.floor(c * weight), least, most).astype(np.int64)

    lo, hi = least / float(positive.max()), (most + 1) / float(positive.min())
    if counts(hi).sum() <= budget:
        return counts(hi)
    for _ in range(64):
        mid = float(np.sqrt(lo * hi))
        if counts(mid).sum() <= budget:
            lo = mid
        else:
            hi = mid
    return counts(lo)


def trace_counts(scene: Scene, tracing: Tracing, origins: np.ndarray, normals: np.ndarray,
                 first: np.ndarray, count: np.ndarray, workers: int,
                 told: Callable[[int], None] | None = None) -> PassSums:
    """The sums (`passes.PassSums`, K texels) of samples ``first[i]`` … ``first[i] +
    count[i] − 1`` of each of the K texels of ``tracing.ids`` (their paths from the (K, 3)
    float32 `origins` about the (K, 3) float32 unit `normals`), traced on `workers`
    threads in items of whole texels (`passes.chunk_bounds`: a texel's paths in one item,
    in sample order, the items smaller as the paths left run out);
    `told(done)`: the texels traced so far, after each of the calling thread's items."""
    first, count = np.asarray(first, np.int64), np.asarray(count, np.int64)
    sums = PassSums(len(count), tracing.settings.channels)
    start = PathStarts(np.arange(len(count), dtype=np.int64), origins, normals)
    bounds = list(chunk_bounds(count, workers))

    def run(item: int) -> None:
        lo, hi = bounds[item]
        paths = count[lo:hi]
        pos = np.repeat(start.texels[lo:hi], paths)
        step = np.arange(len(pos), dtype=np.int64) - np.repeat(np.cumsum(paths) - paths, paths)
        if len(pos):
            trace_chunk(scene, tracing, pos, np.repeat(first[lo:hi], paths) + step, start, sums)

    progress = None if told is None else lambda done: told(bounds[done - 1][1] if done else 0)
    cores.for_items(run, len(bounds), "trace", on_done=progress, workers=workers)
    return sums


def noise_placed(scene: Scene, tracing: Tracing, origins: np.ndarray, normals: np.ndarray,
                 shape: tuple[int, int, int], share: np.ndarray, paths: int, dark_at: int,
                 workers: int, told: Callable[[int], None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Trace `paths` paths a texel on average over the K texels of ``tracing.ids`` (sorted
    flat ids of a (Z, Y, X) lattice; their starts as `trace_counts`'s), placed where the
    picture's noise is (see the module docs): (K,) `share` of the picture each
    (`picture_share`), texels dark on fewer than `dark_at` paths traced on to it (0:
    none, under lights that leave texels honestly dark); `told(done)`: how many texels'
    worth of the budget is traced (rising to K: the first paths count as their share of
    it, the rest as the rest).

    Returns:
        (K, C) sums of the texels' path estimates and (K,) int64 paths behind each.
    """
    k = len(tracing.ids)
    pilot = min(PILOT, paths)
    tracing = dataclasses.replace(tracing, weights=_luminance(tracing.settings.channels))
    zero = np.zeros(k, np.int64)
    first = trace_counts(scene, tracing, origins, normals, zero, np.full(k, pilot, np.int64),
                         workers, _scaled(told, 0, pilot / paths))
    mean = first.sum @ tracing.weights / pilot
    spread = np.sqrt(np.maximum(first.second / pilot - mean ** 2, 0.0))
    weight = neighbour_mean(shape, tracing.ids, spread) * np.sqrt(share)
    count = allocate(weight, paths * k, pilot, max(pilot, CAP * paths))
    sums = _added(first, trace_counts(scene, tracing, origins, normals, zero + pilot,
                                      count - pilot, workers,
                                      _scaled(told, k * pilot / paths, 1 - pilot / paths)))
    if dark_at:
        dark = ~sums.sum.any(axis=1) & (count < dark_at)
        more = np.where(dark, dark_at - count, 0)
        if more.any():
            sums = _added(sums, trace_counts(scene, tracing, origins, normals, count, more,
                                             workers))
            count = count + more
    return sums.sum, count


def _luminance(channels: int) -> np.ndarray:
    """(C,) weights of an irradiance texel's luminance (`baking.lattice.LUMINANCE`)."""
    weights = np.zeros(channels)
    weights[:3] = LUMINANCE
    return weights


def _added(a: PassSums, b: PassSums) -> PassSums:
    """The sums of two passes over the same texels."""
    return PassSums.of(a.sum + b.sum, a.second + b.second, a.n + b.n)


def _scaled(told: Callable[[int], None] | None, before: float, part: float
            ) -> Callable[[int], None] | None:
    """`told` of a pass that is `part` of the budget and follows `before` texels' worth."""
    return None if told is None else lambda done: told(int(before + part * done))
