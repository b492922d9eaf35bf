"""What to bake: active texels, isovalue levels, and where each texel's paths start.

* Active texels ("only what the scene needs"): the corners of lattice cells through which
  a displayable isosurface can pass, i.e. cells whose value span overlaps the iso range.
  Noise is no reason to leave a cell out: marching cubes draws the surface of noise in
  the range (grains in the air of a CT), and a cell left out draws it unlit.
* Sides: a texel is lit on the side of its surface a camera outside the volume sees
  (`baking.sides`: both sides, on alternate texels, where both are seen).
* Targets: a texel is lit on the isosurface of the middle of the isovalues that can read
  it: a display reads a texel from the surfaces that pass through the lattice cells around
  it, those of the isovalues within |∇ρ| × one texel spacing of its value ρ, and only
  isovalues inside the iso range are ever shown (`lit_isovalues`). Where the field is
  gentle that is the texel's own value, the surface through it (the paper's rule); the
  corner texels of the cells a steep surface crosses carry values far outside the range
  (air and metal on either side of an edge) and are lit on the middle of the range's
  isovalues they are near, not on its end: on a noisy scan the surfaces at the range's
  ends are not the displayed one (a head MRI lit on them drew 0.955 of the reference's
  brightness, lit on the middle 0.984). Where no isovalue of the range can reach a
  texel, the range's nearer end. So every level lies inside the range, none is spent on
  isovalues nobody displays.
* Levels: we extract K level surfaces L_0 < ... < L_{K-1}; texel t of target
  L_a ≤ τ_t ≤ L_b spends a fraction w_b = (τ_t − L_a) / (L_b − L_a) of its paths on
  level b and the rest on level a, so its estimate interpolates the two. Its start point
  moves onto the level by Newton steps along the smoothed gradient, a move of
  |L − ρ_t| / |∇ρ|.
* How many levels ("model no more than a scene needs"): the level spacing keeps that move
  below a limit for 90 % of the texels. The limit follows the samples — the error of a
  move grows with its length, the Monte Carlo noise falls as 1/√N, so the limit is
  0.5 voxel at 256 paths per texel and scales as √(256 / N) — and the count is capped so
  that building the level scenes costs at most `SCENE_SHARE` of the tracing (both
  estimated in rays, from the volume, the surface area and the paths: deterministic, so
  the same config gives the same levels on any machine).

Each stage works on blocks of texels on every core (`for_blocks`), the glue between its
compiled kernels included, and each block writes its own rows: the plan is the same bits
on any number of threads.

Length: the stages of one plan share a dozen per-texel arrays (ids, targets, levels,
weights, landing points, sides); split, each part would hand them all back and forth.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numba
import numpy as np

from isolume import volumes
from isolume.baking import bin_kernels, kernels
from isolume.baking.config import BakeConfig
from isolume.baking.environment import ConstantEnvironment
from isolume.baking.errors import BakeError
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.plan_kernels import (
    NEWTON_ITERATIONS,
    UNLANDED,
    NearerLandings,
    field_arrays,
    gradient_norms,
    landed_points,
    landing_offsets,
    lattice_arrays,
    reach_tests,
    start_lift,
)
from isolume.baking.rng import pcg_hash
from isolume.baking.sides import BoxReachAhead, choose_sides
from isolume.volumes import cores
from isolume.volumes.field import normal_stencil
from isolume.volumes.reach import BoxReach

GOLDEN_FRACTION = 0.6180339887498949
MAX_REACH = 4.0
"""Newton moves onto a level are limited to MAX_REACH × max_move voxels."""
MIN_SPAN_FRACTION = 1e-3
"""Cells whose values span less than this fraction of the data range hold no surface worth
baking even in noise-free data (e.g. the far tails of a smooth profile)."""
REFERENCE_SAMPLES = 256
"""Paths per texel at which the automatic move limit is `REFERENCE_MOVE` voxels."""
REFERENCE_MOVE = 0.5
MOVE_LIMITS = (0.25, 2.0)
"""Bounds of the automatic move limit, voxels."""
SCENE_SHARE = 0.2
"""Automatic level counts keep the estimated scene-building cost below this fraction of
the estimated tracing cost."""
SCENE_RAYS_PER_VOXEL = 0.06
SCENE_RAYS_PER_TRIANGLE = 0.5
"""Cost of a level scene in ray equivalents (one incoherent ray traced by one thread):
marching cubes per voxel of the volume, Embree's geometry and BVH per triangle. Measured
on the 2-core machine: 0.17 s for the engine CT's 8.4 M voxels, 0.1 s for its 580 k
triangles, at 1.4 M rays/s per thread."""


@dataclass
class Plan:
    """The texels to bake and their levels.

    Attributes:
        ids: (T,) sorted flat lattice indices of the active texels (`index_type`:
            int32 in a box of fewer than 2³¹ texels).
        rho: (T,) float32 field value at each texel (trilinear), value units; None in a
            plan that is only traced (`traced_only`).
        target: (T,) float32 isovalue each texel is lit at (`lit_isovalues`); None as
            `rho`.
        iso_range: (lo, hi) isovalues the lattice serves.
        levels: (K,) isovalues of the level surfaces, increasing, within `iso_range`.
        lower: (T,) index a of the lower bracketing level (the upper is a + 1), of the
            smallest unsigned type that holds every level's index (uint8 up to 256
            levels: 1 byte a texel).
        weight: (T,) fraction of paths on the upper level, in [0, 1].
        phase: (T,) uint32 per-texel offset of the level-assignment sequence, in units of
            2⁻³² (`kernels.PHASE_UNIT`): in [0, 1) exactly, at 4 bytes a texel.
        active: (Z, Y, X) bool mask of the active texels; None in a plan that is only
            traced (`traced_only`: its texels are `ids`).
        moves: the 50th and 90th percentiles and the largest of the distances from the
            texels to their farther levels, voxels (the lattice metadata's; `MoveFigures`).
        move_limit: the level spacing's move limit, voxels (`move_limit`).
        reach: largest Newton move onto a level, world units (`newton_reach`).
        landing: (T, 2, 3) int16 offset from each texel's centre of where its Newton steps
            land on its lower (0) and upper (1) level, in steps of `reach` /
            `LANDING_STEPS` (`landing_offsets`; `UNLANDED` where a texel does not use the
            level) — the start points' projection, done once; world points by
            `landed_points` (6 bytes a point, exact to half a step: 1.3·10⁻⁴ voxel at a
            reach of 8 voxels).
        high: (T,) bool: the texel is lit on the high-value side of its levels (its
            normals point from low to high values; `baking.sides`).
        unreachable: texels that cannot reach one or both bracketing levels within
            `reach`; they use one level only.

    `weight`, `phase`, `landing` and `high` are None in a plan whose texel records are
    kept in a file (`baking.plan_records.spill`).
    """

    ids: np.ndarray
    rho: np.ndarray | None
    target: np.ndarray | None
    iso_range: tuple[float, float]
    levels: np.ndarray
    lower: np.ndarray
    weight: np.ndarray
    phase: np.ndarray
    active: np.ndarray | None
    moves: MoveFigures
    move_limit: float
    reach: float
    landing: np.ndarray
    high: np.ndarray
    unreachable: int = 0

    def traced_only(self) -> Plan:
        """The plan without what only replanning reads (`rho` and `target`, which the lazy
        viewer compares between plans) and the box's mask of active texels (a lattice
        over the plan's texels has `ids`): 8 bytes an active texel and 1 a texel of the
        box less for a bake that traces the plan it made."""
        return replace(self, rho=None, target=None, active=None)

    def on_upper(self, positions: np.ndarray, samples: np.ndarray) -> np.ndarray:
        """(N,) bool: does sample `samples[i]` of texel `ids[positions[i]]` use the upper
        level? A golden-ratio sequence per texel, so any prefix of N samples puts
        w·N ± O(log N) of them on the upper level (stratified, not random)."""
        x = np.mod(self.phase[positions] * kernels.PHASE_UNIT + samples * GOLDEN_FRACTION, 1.0)
        return x < self.weight[positions]


def select_cells(rho: np.ndarray, lo: float, hi: float, min_span: float,
                 mid: float) -> tuple[np.ndarray, int]:
    """The texels to bake from the (Z, Y, X) texel values `rho`: the corners of the cells
    whose 8 corner values span a range that overlaps [lo, hi] and is wider than
    `min_span`. One compiled pass, in z-slabs of cells on every core (`cores.for_ranges`;
    two slabs may both mark the layer between them: the same True either way).

    Returns:
        active: (Z, Y, X) bool; crossed: how many of those cells the level `mid` passes
        through (corner values on both sides of it).
    """
    active = np.zeros(rho.shape, bool)
    rho = np.ascontiguousarray(rho, np.float32)
    layers = max(rho.shape[0] - 1, 0)
    crossed = np.zeros(layers, np.int64)  # per layer of cells: summed in order below

    def slab(k0: int, k1: int) -> None:
        _select_kernel(rho, float(lo), float(hi), float(min_span), float(mid), active,
                       crossed, k0, k1)

    cores.for_ranges(slab, layers, rho[0].size, "texel values")
    return active, int(crossed.sum())


@numba.njit(nogil=True, cache=True)
def _select_kernel(rho: np.ndarray, lo: float, hi: float, min_span: float, mid: float,
                   active: np.ndarray, crossed: np.ndarray, k0: int, k1: int) -> None:
    """`select_cells` on the cells of layers k0 … k1 − 1: marks `active`, counts the
    selected cells crossing `mid` per layer into `crossed`."""
    for k in range(k0, k1):
        for j in range(rho.shape[1] - 1):
            for i in range(rho.shape[2] - 1):
                cmin = cmax = rho[k, j, i]
                for a in range(2):
                    for b in range(2):
                        for c in range(2):
                            v = rho[k + a, j + b, i + c]
                            cmin = min(cmin, v)
                            cmax = max(cmax, v)
                if cmax >= lo and cmin <= hi and cmax - cmin > min_span:
                    for a in range(2):
                        for b in range(2):
                            for c in range(2):
                                active[k + a, j + b, i + c] = True
                    if cmin <= mid <= cmax and cmax > cmin:
                        crossed[k] += 1


def active_texels(active: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (N,) flat ids (`index_type`) of the True texels of the (Z, Y, X) bool `active`,
    in order (`numpy.flatnonzero`), and their (N,) values in the (Z, Y, X) `rho`:
    counted, then gathered, by z-slabs on every core (`cores.for_ranges`)."""
    layers = active.shape[0]
    counts = np.zeros(layers + 1, np.int64)
    cores.for_ranges(lambda k0, k1: _count_layers(active, counts, k0, k1), layers,
                     active[0].size, "texel values")
    starts = np.cumsum(counts)  # layer k's rows start at starts[k]
    ids = np.empty(int(starts[-1]), index_type(active.size))
    values = np.empty(len(ids), rho.dtype)
    cores.for_ranges(lambda k0, k1: _gather_layers(active, rho, starts, ids, values, k0, k1),
                     layers, active[0].size, "texel values")
    return ids, values


@numba.njit(nogil=True, cache=True)
def _count_layers(active: np.ndarray, counts: np.ndarray, k0: int, k1: int) -> None:
    """counts[k + 1] = the True texels of layer k of `active`, for k0 ≤ k < k1."""
    for k in range(k0, k1):
        n = 0
        for j in range(active.shape[1]):
            for i in range(active.shape[2]):
                n += active[k, j, i]
        counts[k + 1] = n


@numba.njit(nogil=True, cache=True)
def _gather_layers(active: np.ndarray, rho: np.ndarray, starts: np.ndarray, ids: np.ndarray,
                   values: np.ndarray, k0: int, k1: int) -> None:
    """The flat ids and values of layers k0 … k1 − 1's True texels, from each layer's
    first row `starts[k]` of `ids` and `values` (`active_texels`)."""
    ny, nx = active.shape[1], active.shape[2]
    for k in range(k0, k1):
        row = starts[k]
        for j in range(ny):
            for i in range(nx):
                if active[k, j, i]:
                    ids[row] = (k * ny + j) * nx + i
                    values[row] = rho[k, j, i]
                    row += 1


def texel_values(volume: volumes.Volume, geometry: LatticeGeometry) -> np.ndarray:
    """(Z, Y, X) float32 field value at every texel centre: `volumes.value_at` at
    `geometry.centres`, computed on the grid of centres in one compiled pass (no
    volume-sized temporaries)."""
    x, y, z = (geometry.lo[a] + (np.arange(geometry.shape[2 - a]) + 0.5) * geometry.texel_size[a]
               for a in range(3))
    return volumes.values_on_grid(volume, x, y, z)


def make_plan(volume: volumes.Volume, geometry: LatticeGeometry, config: BakeConfig,
              levels: np.ndarray | None = None,
              progress: Callable[..., None] | None = None,
              on_levels: Callable[[np.ndarray], None] | None = None,
              scenes: Callable[[int], object] | None = None,
              traced_only: bool = False) -> Plan:
    """Choose active texels, their targets and the levels for `config` (see the module
    docstring); `levels` (K,) replaces the choice (a resumed bake keeps its file's).
    `progress(stage)` is told each stage as it starts (the viewer shows it), and
    ``progress(stage, fraction)`` how far the long ones (the Newton steps, the side probes,
    the reach tests: minutes on a 512³ CT) have come, a fraction in [0, 1];
    `on_levels(levels)` as soon as the levels are known (the baker starts building the
    scene the side probes start on beside the Newton steps); `scenes(k)` gives the Embree
    scene of level k for the side probes, or None (`choose_sides`); `traced_only`: make
    `Plan.traced_only`'s plan, letting go of what only replanning reads (the box's mask,
    the texels' values and targets: 128 + 315 MB on a 512³ CT) as soon as the levels
    are bracketed, not after the side probes."""
    with BoxReachAhead(volume, config) as box_reach:
        return _planned(volume, geometry, config, levels, progress, on_levels, scenes,
                        traced_only, box_reach)


def _planned(volume: volumes.Volume, geometry: LatticeGeometry, config: BakeConfig,
             levels: np.ndarray | None, progress: Callable[..., None] | None,
             on_levels: Callable[[np.ndarray], None] | None,
             scenes: Callable[[int], object] | None, traced_only: bool,
             box_reach: BoxReachAhead) -> Plan:
    """`make_plan`, whose side probes test against `box_reach`'s flood, begun once the
    box's grid of texel values is let go (`choose_sides`)."""
    say = progress or (lambda _stage, _fraction=None: None)
    vmin, vmax = volume.value_range
    if vmax <= vmin:
        raise BakeError(f"{volume.source or volume.name}: the volume is constant ({vmin:g}); "
                        "there is no isosurface to bake")
    lo, hi = resolved_iso_range(volume, config)
    say("texel values")
    cores.stage("texel values")
    rho = texel_values(volume, geometry)
    min_span = MIN_SPAN_FRACTION * (vmax - vmin)
    active, crossed = select_cells(rho, lo, hi, min_span, 0.5 * (lo + hi))
    ids, texel_rho = active_texels(active, rho)
    if traced_only:
        active = None
    if len(ids) == 0:
        raise BakeError(
            f"{volume.source or volume.name}: no isosurface in --iso-range [{lo:g}, {hi:g}] "
            "(no lattice cell's values span any of it); nothing to bake"
        )
    del rho  # the box's grid (4 bytes a texel): the rest of the plan is per active texel
    box_reach.begin()  # its arrays (5–6 bytes a voxel) need not sit beside that grid
    say("gradients")
    cores.stage("gradients")
    grad = _gradients(volume, geometry, ids)
    target = np.empty(len(ids))

    def targets(block: slice) -> None:
        target[block] = lit_isovalues(texel_rho[block], grad[block] / config.scale, lo, hi)

    for_blocks(targets, len(ids), "lit isovalues")
    h = float(np.mean(volume.spacing))
    limit = move_limit(config)
    cores.stage("levels")
    if levels is None:
        budget = level_budget(volume, geometry, config, crossed, len(ids))
        levels = choose_levels(target, grad, (lo, hi), limit, budget)
    grad = None  # the levels are chosen: its 8 bytes a texel go
    levels = np.asarray(levels, np.float64)
    if on_levels is not None:
        on_levels(levels)
    lower, weight = np.empty(len(ids), np.min_scalar_type(len(levels) - 1)), np.empty(len(ids))

    def bracket(block: slice) -> None:
        lower[block], weight[block] = _bracketing(levels, target[block])

    for_blocks(bracket, len(ids), "bracketing")
    texel_rho, target = (None, None) if traced_only else (texel_rho, target.astype(np.float32))
    # Each texel must reach its bracketing levels by Newton steps along the gradient. Where
    # one cannot be reached (small gradient, or the level surface lies elsewhere: plateaus,
    # thin layers), all paths go to the other; where neither can, to the level whose
    # surface the texel lies *outside* of (the side the normals point to), so the clamped
    # move leaves it floating in front of that surface rather than buried behind it.
    reach = newton_reach(volume, config)
    stage = f"paths onto {len(levels)} levels"
    say(stage)
    cores.stage("paths onto levels")
    uses_lo, uses_hi = weight < 1, weight > 0
    landing = np.full((len(ids), 2, 3), UNLANDED, np.int16)

    def land(block: slice) -> None:
        centres = geometry.centres(ids[block])
        for side, uses in ((0, uses_lo[block]), (1, uses_hi[block])):
            landing[block][uses, side] = landing_offsets(project_to_level(
                volume, centres[uses], levels[lower[block] + side][uses], max_move=reach),
                centres[uses], reach)

    for_blocks(land, len(ids), "newton", lambda fraction: say(stage, fraction))
    stage = f"seen sides on {len(levels)} levels"
    say(stage)
    cores.stage("seen sides")
    high = lit_sides(volume, config, geometry, ids, landing, reach, levels, lower, weight,
                     scenes, lambda fraction: say(stage, fraction), box_reach.get)
    say("reach tests")
    cores.stage("reach tests")
    reaches = _Reaches(volume, config, geometry, ids, reach,
                       max(start_lift(volume, config), 0.0), levels, lower, high)
    ok_lo, move_lo = reaches(0, uses_lo, landing[:, 0])
    say("reach tests", 1 / 3)
    ok_hi, move_hi = reaches(1, uses_hi | ~ok_lo, landing[:, 1])
    say("reach tests", 2 / 3)
    ok_lo, move_lo = reaches(0, ~uses_lo & ~ok_hi, landing[:, 0], ok_lo, move_lo)  # fallback
    say("reach tests", 1.0)
    cores.stage("settle")
    needed = np.empty(len(ids), bool)  # whether a texel reaches the levels it uses
    move = np.empty(len(ids), np.float32)
    phase = np.empty(len(ids), np.uint32)
    seed = np.uint32(config.seed & 0xFFFFFFFF)

    def settle(b: slice) -> None:
        needed[b] = (ok_lo[b] | (weight[b] == 1)) & (ok_hi[b] | (weight[b] == 0))
        weight[b], move[b] = _settled(weight[b], needed[b], ok_lo[b], ok_hi[b], high[b],
                                      move_lo[b], move_hi[b], h)
        phase[b] = pcg_hash(ids[b].astype(np.uint32) ^ seed)

    for_blocks(settle, len(ids), "settle")
    return Plan(ids, texel_rho, target, (lo, hi), levels, lower, weight, phase,
                active, MoveFigures(move), limit, reach, landing, high,
                int(np.count_nonzero(~needed)))


class MoveFigures:
    """The 50th and 90th percentiles and the largest of a plan's (T,) float32 `move`s onto
    their farther levels, voxels (`Plan.moves`), found on a pool thread beside what
    follows the plan (a partition of every texel's move: 0.7 s of one core for the 512³
    foot's 41 M texels), or at once with one thread or inside the pool."""

    def __init__(self, move: np.ndarray) -> None:
        self._ahead = cores.ahead("move figures", _move_figures, move)
        self._figures = _move_figures(move) if self._ahead is None else None

    def figures(self) -> tuple[float, float, float]:
        """(p50, p90, largest), voxels (waited for where found beside)."""
        if self._figures is None:
            self._figures = self._ahead.wait()
        return self._figures

    def __eq__(self, other: object) -> bool:
        """Equal figures (two plans of the same texels compare equal)."""
        return isinstance(other, MoveFigures) and self.figures() == other.figures()

    __hash__ = None  # type: ignore[assignment]  # equal by value, and not frozen


def _move_figures(move: np.ndarray) -> tuple[float, float, float]:
    """(p50, p90, largest) of (T,) `move`, T ≥ 1."""
    return (*(float(v) for v in np.percentile(move, [50, 90])), float(move.max()))


def index_type(count: int) -> type:
    """The type of indices into `count` items — a plan's flat lattice ids in a box of
    `count` texels, or its positions: int32 (4 bytes each) while they fit, else int64.
    Compiled kernels read ids as int64 chunk by chunk (`baking.passes.trace_texels`,
    `baking.side_kernels.open_counts`)."""
    return np.int32 if count <= np.iinfo(np.int32).max else np.int64


def _bracketing(levels: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) int64 index a of the lower of the two of the (K,) `levels` around each of the
    (N,) isovalues `target` (the upper is a + 1), and (N,) float64 the fraction of the way
    from level a to a + 1, in [0, 1]."""
    lower = np.clip(np.searchsorted(levels, target, side="right") - 1, 0, len(levels) - 2)
    return lower, np.clip((target - levels[lower]) / (levels[lower + 1] - levels[lower]), 0, 1)


def _settled(weight: np.ndarray, needed: np.ndarray, ok_lo: np.ndarray, ok_hi: np.ndarray,
             high: np.ndarray, move_lo: np.ndarray, move_hi: np.ndarray, h: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """The (N,) weights of texels once the levels they reach are known, and (N,) float32
    their moves onto their farther level, voxels. A texel that cannot reach a level it
    needs (`needed` False) puts all its paths on the one it reaches (`ok_lo`, `ok_hi`),
    or where it reaches neither on the level whose lit side it lies on (`high`)."""
    outside = np.where(high, 0.0, 1.0)
    weight = np.where(needed, weight, np.where(ok_hi, 1.0, np.where(ok_lo, 0.0, outside)))
    move = (np.maximum(np.where(weight < 1, move_lo, 0.0), np.where(weight > 0, move_hi, 0.0))
            / h).astype(np.float32)
    return weight, move


def lit_isovalues(rho: np.ndarray, span: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(T,) float64 isovalue each texel is lit on: the middle of the isovalues of the range
    [`lo`, `hi`] whose surfaces pass within a texel spacing of it, ρ ± `span` (`rho` (T,)
    its value, `span` (T,) |∇ρ| × the texel spacing, value units), or the range's nearer
    end where none does."""
    rho = np.asarray(rho, np.float64)
    first, last = np.maximum(lo, rho - span), np.minimum(hi, rho + span)
    return np.where(first <= last, 0.5 * (first + last), np.clip(rho, lo, hi))


def lit_sides(volume: volumes.Volume, config: BakeConfig, geometry: LatticeGeometry,
              ids: np.ndarray, landing: np.ndarray, reach: float, levels: np.ndarray,
              lower: np.ndarray, weight: np.ndarray,
              scenes: Callable[[int], object] | None = None,
              progress: Callable[[float], None] | None = None,
              box_reach: Callable[[], BoxReach] | None = None) -> np.ndarray:
    """(T,) bool: is each texel lit on the high-value side of its surfaces
    (`baking.sides.choose_sides`, probed where it lands on its nearer level: `landing`
    (T, 2, 3) as `Plan.landing` with its `reach`, set for the levels the texel uses;
    `scenes`, `progress` and `box_reach` as there)?"""
    if config.sides == "normals":
        return np.full(len(ids), bool(config.flip_normals))
    upper = weight >= 0.5
    found = np.where(upper, landing[:, 1, 0] != UNLANDED, landing[:, 0, 0] != UNLANDED)
    return choose_sides(volume, config, geometry, ids,
                        NearerLandings(geometry, ids, landing, upper, reach), found, levels,
                        lower + upper, scenes, progress, box_reach)


def rounded_landing(points: np.ndarray, centres: np.ndarray, reach: float) -> np.ndarray:
    """(N, 3) float64 world points (N, 3) as `Plan.landing` keeps them: where the paths of
    a plan start from, whoever projected them (`baking.passes.start_points`)."""
    return landed_points(landing_offsets(points, centres, reach), centres, reach)


def resolved_iso_range(volume: volumes.Volume, config: BakeConfig) -> tuple[float, float]:
    """The iso range a bake of `volume` serves: `config.iso_range` (checked against the
    data) or `default_iso_range`."""
    vmin, vmax = volume.value_range
    lo, hi = config.iso_range if config.iso_range is not None else default_iso_range(volume)
    if hi <= vmin or lo >= vmax:
        raise BakeError(
            f"--iso-range {lo:g} {hi:g} does not overlap the data range [{vmin:g}, {vmax:g}] "
            f"of {volume.source or volume.name}"
        )
    return max(lo, vmin), min(hi, vmax)


def newton_reach(volume: volumes.Volume, config: BakeConfig) -> float:
    """Largest Newton move of a texel onto a level, world units: `MAX_REACH` × the move
    limit, and at least the diagonal of a lattice cell (a texel's target surface passes
    through one of its cells)."""
    h = float(np.mean(volume.spacing))
    cell = LatticeGeometry.for_volume(volume, config.scale).texel_size
    return max(MAX_REACH * move_limit(config) * h, float(np.linalg.norm(cell)))


def served_range(meta: dict[str, Any]) -> tuple[float, float] | None:
    """The iso range a lattice (its metadata `meta`) was baked for, or None for files
    written before texels were lit on values clamped to it (they serve any isovalue)."""
    served = meta.get("plan", {}).get("iso_range")
    return None if served is None else (float(served[0]), float(served[1]))


def outside_served_range(meta: dict[str, Any], iso: float, source: str) -> str:
    """"" when a lattice baked with metadata `meta` (from `source`) serves isovalue `iso`;
    else a one-line message saying so and what to do."""
    served = served_range(meta)
    if served is None:
        return ""
    lo, hi = served
    tolerance = 1e-6 * max(abs(lo), abs(hi), 1.0)
    if lo - tolerance <= iso <= hi + tolerance:
        return ""
    nearest = lo if iso < lo else hi
    return (f"{source}: baked for isovalues {lo:g} to {hi:g}; at isovalue {iso:g} its light "
            f"would be that of the surface at {nearest:g} (wrong shadows and shading): bake "
            f"with --iso-range covering {iso:g}, or render without the lattice")


def move_limit(config: BakeConfig) -> float:
    """Largest Newton move onto a level that the level spacing allows (90 % of texels),
    voxels: `config.max_move`, or when that is None `REFERENCE_MOVE` × √(256 / samples)
    within `MOVE_LIMITS` (a move's error need not be smaller than the noise), or
    `REFERENCE_MOVE` for a `noise_free` bake."""
    if config.max_move is not None:
        return float(config.max_move)
    if noise_free(config):
        return REFERENCE_MOVE
    scaled = REFERENCE_MOVE * math.sqrt(REFERENCE_SAMPLES / config.plan_samples)
    return float(np.clip(scaled, *MOVE_LIMITS))


def as_planned(config: BakeConfig, meta: dict[str, Any]) -> BakeConfig:
    """`config` with the move limit a lattice was planned with (its metadata's
    ``plan["move_limit_voxels"]``) as `BakeConfig.max_move`: a resumed bake moves its
    texels onto the kept levels as far as the paths already traced were moved, even where
    its sample count (which sets the limit, `move_limit`) differs. `config` itself where
    `meta` records none (a new bake)."""
    plan = meta.get("plan", {})
    if "move_limit_voxels" not in plan:
        return config
    return replace(config, max_move=float(plan["move_limit_voxels"]))


def levels_follow_samples(config: BakeConfig) -> bool:
    """True when `config`'s levels depend on its sample count (the automatic policy): a
    bake resumed with more samples then keeps the levels of its file, and differs from a
    fresh bake of the larger count."""
    return config.max_move is None and not noise_free(config)


def noise_free(config: BakeConfig) -> bool:
    """True when every path of a texel gives the same estimate: point and directional
    lights only (one shadow ray each), no bounces. The levels are then the only error,
    and are neither loosened by the samples nor capped by the scenes' cost."""
    return config.lighting.environment is None and config.bounces == 0


def level_budget(volume: volumes.Volume, geometry: LatticeGeometry, config: BakeConfig,
                 crossed: int, texels: int) -> int:
    """Most levels worth building: `config.max_levels`, and with an automatic move limit
    (`config.max_move` None; not `noise_free`) at most as many as cost `SCENE_SHARE` of
    the tracing.

    Tracing: texels × samples × rays per path (one per vertex, twice that where light is
    sampled at vertices). A scene: marching cubes over the volume plus Embree's work per
    triangle, two per voxel face crossed by the mid-range level (`crossed` selected
    lattice cells, `select_cells`, scaled to voxels).
    """
    if config.max_move is not None or noise_free(config):
        return config.max_levels
    lighting = config.lighting
    sampled = bool(lighting.lights) or not isinstance(lighting.environment, ConstantEnvironment)
    rays = texels * config.plan_samples * (config.bounces + 1) * (2 if sampled else 1)
    voxels_per_cell = float(np.prod(np.asarray(volume.data.shape) / geometry.shape))
    triangles = 2 * crossed * voxels_per_cell ** (2 / 3)
    scene = SCENE_RAYS_PER_VOXEL * volume.data.size + SCENE_RAYS_PER_TRIANGLE * triangles
    return int(np.clip(SCENE_SHARE * rays / scene, 2, config.max_levels))


def choose_levels(target: np.ndarray, grad_per_voxel: np.ndarray,
                  iso_range: tuple[float, float], move: float, budget: int,
                  bins: int = 512) -> np.ndarray:
    """(K,) level isovalues covering the texels' targets (which lie in `iso_range`), denser
    where gradients are small.

    A texel of gradient |∇ρ| (value per voxel) between levels ΔL apart moves up to
    ΔL / |∇ρ| voxels onto one of them. Over a fine histogram of the targets, each bin asks
    for a level spacing of `move` × (10th percentile of |∇ρ| of its texels); levels are
    then placed at equal steps of the accumulated level density ∫ dρ / spacing(ρ), so 90 %
    of the texels of every value range move at most `move` voxels. When that needs more
    than `budget` levels, the densest ranges are capped (water-filling), so no range
    starves.
    """
    lo, hi = float(max(target.min(), iso_range[0])), float(min(target.max(), iso_range[1]))
    if hi <= lo:
        return np.array([lo, lo + max(abs(lo) * 1e-6, 1e-6)])
    edges = np.linspace(lo, hi, bins + 1)
    which = np.empty(len(target), np.min_scalar_type(bins))

    def bin_of(block: slice) -> None:
        which[block] = np.clip(np.searchsorted(edges, target[block], side="right") - 1, 0,
                               bins - 1)

    for_blocks(bin_of, len(target), "levels")
    spacing = move * np.maximum(_binned_percentile(which, grad_per_voxel, bins, 10, np.nan),
                                1e-12 * (hi - lo))
    if np.isnan(spacing).any():  # empty bins: the 10th percentile of every texel's
        spacing = np.where(np.isnan(spacing), move * max(
            float(np.percentile(grad_per_voxel, 10)), 1e-12 * (hi - lo)), spacing)
    per_bin = (edges[1:] - edges[:-1]) / spacing  # levels each bin asks for
    per_bin = _water_fill(per_bin, budget - 1)
    density = np.concatenate([[0.0], np.cumsum(per_bin)])
    count = int(np.clip(np.ceil(density[-1]) + 1, 2, budget))
    return np.interp(np.linspace(0, density[-1], count), density, edges)


def _binned_percentile(which: np.ndarray, values: np.ndarray, bins: int, q: float,
                       empty: float) -> np.ndarray:
    """(bins,) the q-th percentile of the (N,) `values` in each bin (`which`, (N,) bin
    indices), as `np.percentile`'s linear method gives it; `empty` for empty bins. The
    values grouped by bin (a radix sort of the bin indices), then in each bin the two
    ranks the percentile lies between put in place (a partition, not a sort: a bin may
    hold half the texels): the values there are those `np.lexsort((values, which))`
    ranks there, holding two arrays of N at a time."""
    ranked, counts = grouped_by_bin(which, values, bins)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    several = np.flatnonzero(counts > 1)
    position = starts + q / 100 * np.maximum(counts - 1, 0)
    below = np.floor(position).astype(np.int64)
    above = np.minimum(below + 1, starts + np.maximum(counts - 1, 0))

    def rank_bin(i: int) -> None:  # numpy's partition releases the GIL: bins on every core
        b = several[i]
        ranked[starts[b]:starts[b] + counts[b]].partition(
            np.unique([below[b] - starts[b], above[b] - starts[b]]))

    cores.for_items(rank_bin, len(several), "levels")
    t = position - below
    if len(ranked) == 0:
        return np.full(bins, empty)
    a, b = ranked[np.minimum(below, len(ranked) - 1)], ranked[np.minimum(above,
                                                                         len(ranked) - 1)]
    diff = b - a
    out = np.where(t >= 0.5, b - diff * (1 - t), a + diff * t)  # numpy's _lerp
    return np.where(counts > 0, out, empty)


def grouped_by_bin(which: np.ndarray, values: np.ndarray | None, bins: int,
                   kind: str = "levels", shift: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the `values` grouped by bin (``which >> shift``, `which` (N,) ints, bins <
    `bins`) in their order within each bin (as ``values[np.argsort(which >> shift,
    kind="stable")]``; `values` None: the indices 0 … N − 1, as int64), and the (bins,)
    counts: a counting sort in blocks on every core (each block's counts, then each
    block's values put where the blocks before it end in each bin), its work items named
    `kind`. The kernels take each element's bin (and its index) as they go: the memory
    is the (N,) result and the blocks' counts."""
    parts = cores.blocks(len(which), PLAN_BLOCK)
    counts = np.zeros((len(parts), bins), np.int64)
    cores.for_items(lambda b: bin_kernels.count_bins(which, shift, parts[b].start,
                                                     parts[b].stop, counts[b]),
                    len(parts), kind)
    totals = counts.sum(axis=0)
    places = np.cumsum(counts, axis=0) - counts + (np.cumsum(totals) - totals)
    ranked = np.empty(len(which), np.int64 if values is None else values.dtype)

    def scatter(b: int) -> None:
        lo, hi = parts[b].start, parts[b].stop
        if values is None:
            bin_kernels.scatter_index_by_bin(which, shift, lo, hi, places[b], ranked)
        else:
            bin_kernels.scatter_by_bin(which, shift, values, lo, hi, places[b], ranked)

    cores.for_items(scatter, len(parts), kind)
    return ranked, totals


def _water_fill(demand: np.ndarray, budget: float) -> np.ndarray:
    """Cap each bin's demand at one common level c so the total fits `budget`: value ranges
    that ask for few levels get all they ask for; the greedy ones share what is left."""
    if demand.sum() <= budget:
        return demand
    lo, hi = 0.0, float(demand.max())
    for _ in range(60):  # bisection on the cap
        cap = 0.5 * (lo + hi)
        lo, hi = (cap, hi) if np.minimum(demand, cap).sum() < budget else (lo, cap)
    return np.minimum(demand, lo)


def default_iso_range(volume: volumes.Volume) -> tuple[float, float]:
    """Isovalues a user is likely to show: the suggested ones with a margin of a quarter of
    their spread on either side (±15 % of the data range around a single suggestion),
    within the data range."""
    vmin, vmax = volume.value_range
    suggested = volumes.suggest_isovalues(volume)
    if not suggested:
        return vmin, vmax
    if len(suggested) > 1:
        spread = max(suggested) - min(suggested)
    else:
        spread = 0.6 * (vmax - vmin)
    return max(vmin, min(suggested) - 0.25 * spread), min(vmax, max(suggested) + 0.25 * spread)


def project_to_level(volume: volumes.Volume, points: np.ndarray, level: float | np.ndarray,
                     max_move: float, iterations: int = NEWTON_ITERATIONS, smooth: bool = True
                     ) -> np.ndarray:
    """(N, 3) points moved onto ρ = level (a scalar or (N,) values) by Newton steps along
    the smoothed gradient (the plain one if not `smooth`).

    Each step moves by (level − ρ) ∇ρ / |∇ρ|²; the total move is clamped to `max_move`
    world units (where the gradient is tiny the level is far and the texel is poor
    anyway).
    """
    return volumes.newton_to_level(volume, points, level, max_move, iterations, smooth)


def _gradients(volume: volumes.Volume, geometry: LatticeGeometry, ids: np.ndarray
               ) -> np.ndarray:
    """(T,) |∇ρ| at the centres of texels `ids`, value units per voxel (`choose_levels`)."""
    h = float(np.mean(volume.spacing))
    grad = np.empty(len(ids))
    lattice, field = lattice_arrays(geometry), field_arrays(volume)
    w = normal_stencil(volume, True)[1]

    def norms(block: slice) -> None:
        gradient_norms(lattice, ids[block], field, w, h, grad[block])

    for_blocks(norms, len(ids), "gradients")
    return grad


PLAN_BLOCK = 1 << 15
"""Texels whose centres, gradients and Newton moves one work item of the plan takes
(`for_blocks`): its temporaries hold tens of bytes per texel of a block a thread, not of
the plan, and a 256³ CT's plan is hundreds of items, handed out to whichever core is
free (a block of stalled Newton points holds up one thread)."""


def for_blocks(work: Callable[[slice], None], count: int, kind: str,
               progress: Callable[[float], None] | None = None) -> None:
    """`work(block)` for blocks of at most `PLAN_BLOCK` of `count` texels on every core
    (`cores.for_blocks`: the numpy between the compiled kernels runs in the items too, and
    each block writes its own rows, so the plan is the same bits on any number of
    threads)."""
    cores.for_blocks(work, count, PLAN_BLOCK, kind, progress)


@dataclass(frozen=True)
class _Reaches:
    """The reach tests of a plan's (T,) texels `ids` (`plan_kernels.reach_tests`), block
    by block (`for_blocks`): can a texel be moved onto its level within `reach` world
    units, and do its paths start on its lit side (`high` (T,): the high-value side) of
    that level's surface?

    Not where the level is the thin shell around a ridge or a valley whose extreme barely
    passes it — a cooling fin whose peak lies just below the displayed isovalue, next to
    the casing it stands on: the smoothed normal there is the casing's, points across the
    shell, the start point (`lift` world units along it, as `baking.passes.start_points`
    moves it) lands inside it and every path is blocked (such texels came out black, and
    the casing wall beside the fin dark: the worst error of the synthetic engine). Only
    the move is checked where `lift` is 0.
    """

    volume: volumes.Volume
    config: BakeConfig
    geometry: LatticeGeometry
    ids: np.ndarray
    reach: float
    lift: float
    levels: np.ndarray
    lower: np.ndarray
    high: np.ndarray

    def __call__(self, side: int, which: np.ndarray, landing: np.ndarray,
                 ok: np.ndarray | None = None, moved: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The tests of the (T,) `which` texels from their centres onto their lower (`side`
        0) or upper (1) level (landed within `plan_kernels.CONVERGED_FRACTION` of the
        spacing of their two levels); the others keep `ok` (default True) and `moved`
        (default 0).

        Args:
            landing: (T, 3) int16 offsets as `Plan.landing`'s of that side, written where
                a texel had none (projected by Newton steps).

        Returns:
            ok: (T,) bool; moved: (T,) float32 length of the (clamped) move, world units.
        """
        count = len(self.ids)
        ok = np.ones(count, bool) if ok is None else ok.copy()
        moved = np.zeros(count, np.float32) if moved is None else moved.copy()
        volume = self.volume
        fixed = (lattice_arrays(self.geometry), self.ids, self.lower, self.levels, side,
                 self.high, which, landing, ok, moved, self.reach, self.lift,
                 field_arrays(volume), normal_stencil(volume, True)[1],
                 normal_stencil(volume, self.config.normals == "smooth")[1])
        value_type = np.result_type(volume.data.dtype, np.float32)  # `volumes.value_at`'s

        def block(b: slice) -> None:
            reach_tests(*fixed, np.empty(1, value_type), b.start, b.stop)

        for_blocks(block, count, "reach tests")
        return ok, moved
