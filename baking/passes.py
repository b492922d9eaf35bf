"""The pieces of a bake's pass that every tracing backend shares (`baking.backend`).

A pass brings some texels up to a sample count. Texels trace their pending paths on each
of the two isovalue levels that bracket them (`lay_out_level`: the texels and their path
counts on one level; a chunk's positions, sample indices and start points are made when
it is traced, so a layout costs bytes per texel, not per path) on the level's scene
(`level_scene`), in chunks of whole texels (`chunk_bounds`, `trace_texels`); a chunk's
per-texel sums, formed from zero, go to the texels' pass sums (`PassSums`: their
lower-level paths, then their upper-level ones), and a texel complete on its upper level
is merged into the lattice (`commit_sums`). A texel's paths and start point depend on
that texel alone and its sums are added in sample order, so the lattice is the same bits
whoever traces the chunks and whichever texels are committed together. A texel's facing
(`landing_facing`, committed by `commit_facing`) comes from the plan alone, so it is the
same bits too.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.baking import kernels, octahedral
from isolume.baking.config import BakeConfig
from isolume.baking.integrator import (
    NO_STRATA,
    PathSettings,
    TracingLights,
    WholePaths,
    trace_paths,
    trace_whole_paths,
)
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.plan import (
    GOLDEN_FRACTION,
    Plan,
    newton_reach,
    project_to_level,
    rounded_landing,
)
from isolume.baking.plan_kernels import LandedStarts
from isolume.baking.rays import RayStats
from isolume.volumes import cores

if TYPE_CHECKING:  # embreex is imported only when a bake runs
    from isolume.baking.plan_lattice import PlanLattice
    from isolume.baking.plan_records import PlanRecords, TexelRecords
    from isolume.baking.trace import Scene

PATHS_PER_CHUNK = 32768
"""Paths one tracing work item traces, at most (`chunk_bounds`): ~2 MB of per-path arrays
a worker. The Python around a chunk's compiled calls (their dispatch: ~0.17 ms a chunk
however many paths) holds the GIL, 1.6 % of a 64-path bake's tracing on one thread; each
thread more asks for the GIL that much more often."""
MIN_PATHS_PER_CHUNK = 4096
"""Paths of a level's last chunks, at least (a few milliseconds of tracing)."""
GUIDED_WORKERS = 16
"""Workers `chunk_bounds` cuts a level's last chunks for, at least."""


class PassSums:
    """Per-texel sums of one pass over some texels (float64): ``sum`` (A, C), ``second``
    (A,) (squared brightness) and ``n`` (A,) (paths)."""

    def __init__(self, count: int, channels: int) -> None:
        self.sum: np.ndarray = np.zeros((count, channels))
        self.second: np.ndarray = np.zeros(count)
        self.n: np.ndarray = np.zeros(count, np.int64)

    @classmethod
    def of(cls, sums: np.ndarray, second: np.ndarray, n: np.ndarray) -> PassSums:
        """Sums made elsewhere: (A, C) `sums`, (A,) `second` and (A,) `n`."""
        out = cls(0, sums.shape[1])
        out.sum, out.second, out.n = sums, second, n
        return out

    def rows(self, these: np.ndarray) -> PassSums:
        """The sums of the texels selected by `these`: a copy for a bool mask or indices,
        views that add into these sums for a slice."""
        return PassSums.of(self.sum[these], self.second[these], self.n[these])

    def copy(self) -> PassSums:
        """These sums in arrays of their own (not views of another's)."""
        return PassSums.of(self.sum.copy(), self.second.copy(), self.n.copy())

    def add(self, positions: np.ndarray, sums: PassSums) -> None:
        """Add `sums` (N texels' sums, formed from zero) to those at (N,) distinct
        `positions` (`kernels.add_rows`: one compiled call, numpy's float64 additions)."""
        kernels.add_rows(np.asarray(positions), self.sum, self.second, self.n, sums.sum,
                         sums.second, sums.n)


def rows_at(rows: np.ndarray | None, positions: np.ndarray) -> np.ndarray:
    """The lattice rows of the texels at plan `positions` (`rows` None: the positions)."""
    return positions if rows is None else rows[positions]


def commit_sums(lattice: Lattice | PlanLattice, ids: np.ndarray, acc: PassSums,
                slots: np.ndarray) -> int:
    """Merge the pass sums at (K,) `slots` of `acc` — of texels at (A,) rows `ids` of the
    lattice's flattened arrays — into the lattice's running means and clear them
    (`kernels.commit_means`: compiled, and the GIL stays free for the tracing threads; a
    block of `COMMIT_BLOCK` slots an item on every core, each slot its own texel).

    Returns:
        how many of them had no sample before.
    """
    ids, slots = np.asarray(ids, np.int64), np.asarray(slots, np.int64)
    fresh: dict[int, int] = {}  # by block

    def merge(block: slice) -> None:
        fresh[block.start] = kernels.commit_means(
            ids, slots[block], lattice.values.reshape(-1, lattice.values.shape[-1]),
            lattice.samples.reshape(-1), lattice.second.reshape(-1), acc.sum, acc.second,
            acc.n)

    cores.for_blocks(merge, len(slots), COMMIT_BLOCK, "commit", least=cores.GLUE_BLOCK)
    return sum(fresh.values())


def landing_facing(volume: volumes.Volume, geometry: LatticeGeometry, config: BakeConfig,
                   reach: float, records: TexelRecords) -> np.ndarray:
    """(P, 2) uint8 facings (`baking.octahedral`) of P texels (their plan `records`): the
    mean of their start normals on their two levels (`start_points`' normals at
    `Plan.landing`, kept in steps of `reach`), weighted like their samples (1 − weight,
    weight); unknown where that mean vanishes."""
    share = np.stack([1 - records.weight, records.weight], axis=1)
    mean = np.zeros((len(records.ids), 3))
    starts = LandedStarts.of(volume, geometry, config, reach)
    for side in (0, 1):
        used = np.flatnonzero(share[:, side] > 0)
        if len(used):
            _, normals = starts.points(records.ids, used, np.full(len(used), side == 1),
                                       records.landing, records.high)
            mean[used] += share[used, side, None] * normals
    return octahedral.encode(mean)


def lit_normals(volume: volumes.Volume, config: BakeConfig, points: np.ndarray,
                high: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit normals at (N, 3) world points on a level, towards each point's
    lit side: lower values, higher where `high` (N,) bool (`Plan.high`)."""
    normals = volumes.normals_at(volume, points,
                                 smooth=config.normals == "smooth").astype(np.float64)
    return np.where(np.asarray(high, bool)[:, None], -normals, normals)


def commit_facing(lattice: Lattice | PlanLattice, volume: volumes.Volume,
                  config: BakeConfig, plan: Plan, records: PlanRecords,
                  positions: np.ndarray, rows: np.ndarray | None,
                  unsampled: bool = True) -> None:
    """Set the facings (`landing_facing`) of the texels at plan `positions` about to be
    committed that have none yet, or no samples yet (a texel reset by another plan; not
    where `unsampled` is False: their facings are this plan's), from the plan's
    `records`; `rows`: the (T,) rows of the plan's texels in the lattice's flattened
    arrays (a `Lattice`: the plan's ids), None where they are the plan positions (a
    `PlanLattice`). `FACING_BLOCK` texels at a time."""
    flat = rows_at(rows, positions)
    codes = lattice.facing.reshape(-1, 2)
    todo = ~octahedral.known(codes[flat])
    if unsampled:
        todo |= lattice.samples.reshape(-1)[flat] == 0
    todo = np.flatnonzero(todo)

    def facings(part: slice) -> None:
        block = todo[part]
        codes[flat[block]] = landing_facing(volume, lattice.geometry, config, plan.reach,
                                            records.of(positions[block]))

    cores.for_blocks(facings, len(todo), FACING_BLOCK, "commit", least=cores.GLUE_BLOCK)


FACING_BLOCK = 1 << 17
"""Texels whose facings one item of `commit_facing` makes, at most (its temporaries: ~200
bytes a texel of a block, 26 MB, where a batch commits a million texels at once; blocks
go to every core, each writing its own texels' codes)."""
COMMIT_BLOCK = 1 << 16
"""Pass-sum slots one item of `commit_sums` merges, at most."""


def chunk_bounds(counts: np.ndarray, workers: int) -> Iterator[tuple[int, int]]:
    """(lo, hi) slices of a level's texels (`LevelPaths`) of (K,) path `counts`: chunks of
    whole texels (a texel's paths stay in one chunk, so its sum is added in sample order
    whatever the number of workers).

    Guided sizes: each chunk takes 1/(2·w) of the paths left, w the workers but at least
    `GUIDED_WORKERS`, between MIN_PATHS_PER_CHUNK and PATHS_PER_CHUNK (up to the end of
    the texel at the cut), so a level ends with small chunks and no worker waits long for
    the last one — and a timeline recorded on few threads holds items small enough to
    replay on many (`volumes.cores`).
    """
    ends = np.cumsum(counts)
    total = int(ends[-1]) if len(ends) else 0
    share = 2 * max(workers, GUIDED_WORKERS)
    lo, done = 0, 0
    while lo < len(counts):
        size = min(PATHS_PER_CHUNK, max(MIN_PATHS_PER_CHUNK, (total - done) // share))
        hi = min(int(np.searchsorted(ends, done + size, side="left")) + 1, len(counts))
        yield lo, hi
        lo, done = hi, int(ends[hi - 1])


def start_points(volume: volumes.Volume, centres: np.ndarray, level: float,
                 config: BakeConfig, high: np.ndarray, on_level: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Texel centres (N, 3) moved onto a level surface (at most the plan's `newton_reach`)
    and offset along the normal of their lit side (`high` (N,): `Plan.high`). `on_level`
    (N, 3): where that move lands, when the plan already projected them (`Plan.landing`:
    the same computation, and the same rounding).

    Returns:
        origins (N, 3) world, normals (N, 3) unit (high → low values, low → high where
        `high`).
    """
    h = float(np.mean(volume.spacing))
    if on_level is None:
        reach = newton_reach(volume, config)
        on_level = rounded_landing(project_to_level(volume, centres, level, max_move=reach),
                                   centres, reach)
    normals = lit_normals(volume, config, on_level, high)
    return on_level + config.offset * h * normals, normals


@dataclass(frozen=True)
class PathStarts:
    """Where the paths of some texels of one level start: per texel, sorted by texel
    position.

    Attributes:
        texels: (T,) sorted texel positions (indices into the `Tracing.ids` they are
            traced with).
        origins: (T, 3) float32 start points (world), normals: (T, 3) float32 unit.
    """

    texels: np.ndarray
    origins: np.ndarray
    normals: np.ndarray


@dataclass(frozen=True)
class LevelPaths:
    """The pending paths of one level, by texel: (K,) sorted plan positions `texels`,
    whether the level is their `upper` one (K,) bool, and their path `counts` (K,); the
    plan's (T_all,) `done`, `remaining`, `phase`, `weight` they are drawn from
    (`kernels.level_texels`)."""

    texels: np.ndarray
    upper: np.ndarray
    counts: np.ndarray
    done: np.ndarray
    remaining: np.ndarray
    phase: np.ndarray
    weight: np.ndarray

    def of(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(P,) texels (0 … hi − lo − 1: of texels lo … hi − 1), (P,) sample indices and
        (P,) strata of the paths of texels lo … hi − 1, sorted by texel, samples
        ascending (`kernels.texel_paths`)."""
        return kernels.texel_paths(self.texels[lo:hi], self.upper[lo:hi],
                                   self.counts[lo:hi], self.done, self.remaining,
                                   self.phase, self.weight, GOLDEN_FRACTION)


@dataclass(frozen=True)
class LevelStarts:
    """The start points of a level's texels (`LevelPaths.texels`, `LevelPaths.upper`),
    made a chunk of texels at a time as it is traced (`start_points`: each texel's from
    its own data alone), so that 24 bytes a texel exist for the texels being traced only,
    not for a whole level and the next one laid out ahead (tens of millions of texels on
    the largest levels of a 512³ CT). Arguments as `lay_out_level`'s; `reach`, the
    `newton_reach` that `landing` is kept in steps of."""

    volume: volumes.Volume
    geometry: LatticeGeometry
    config: BakeConfig
    iso: float
    ids: np.ndarray
    high: np.ndarray
    landing: np.ndarray | None
    texels: np.ndarray
    upper: np.ndarray
    reach: float

    @functools.cached_property
    def _landed(self) -> LandedStarts:
        """The level's `LandedStarts`, made for its first chunk."""
        return LandedStarts.of(self.volume, self.geometry, self.config, self.reach)

    def of(self, lo: int, hi: int) -> PathStarts:
        """The `PathStarts` of the level's texels lo … hi − 1, numbered 0 … hi − lo − 1:
        from the plan's landings in one compiled call (`plan_kernels.landed_starts`, the
        operations of `start_points`), else projected here."""
        texels = self.texels[lo:hi]
        if self.landing is not None:  # `here` lands on its lower level, `below` upper
            origins, normals = self._landed.points(self.ids, texels, self.upper[lo:hi],
                                                   self.landing, self.high)
            return PathStarts(np.arange(hi - lo, dtype=np.int64), origins, normals)
        origins, normals = start_points(self.volume, self.geometry.centres(self.ids[texels]),
                                        self.iso, self.config, self.high[texels])
        return PathStarts(np.arange(hi - lo, dtype=np.int64), origins.astype(np.float32),
                          normals.astype(np.float32))


def lay_out_level(volume: volumes.Volume, geometry: LatticeGeometry, config: BakeConfig,
                  iso: float, ids: np.ndarray, phase: np.ndarray, weight: np.ndarray,
                  high: np.ndarray, here: np.ndarray, below: np.ndarray, done: np.ndarray,
                  remaining: np.ndarray, landing: np.ndarray | None = None
                  ) -> tuple[LevelPaths, LevelStarts]:
    """The pending paths of the level surface ρ = `iso` and how their texels' start points
    are made (a local bake lays out whole levels with it, a cluster task its own texels).
    Each texel's paths and start point depend on that texel alone.

    Args:
        ids, phase, weight, high: (T,) the plan's lattice ids, level phases, upper
            weights and lit sides, of all its texels or of any subset (positions then
            index the subset).
        here, below, done, remaining: as `kernels.level_texels` (positions into `ids`).
        landing: (T, 2, 3) the plan's `Plan.landing` (offsets from the texel centres) of
            the same texels, or None to project them here (cluster tasks, which are not
            sent it).

    Returns:
        the level's paths by texel and their texels' `LevelStarts`.
    """
    texels, upper, counts = kernels.level_texels(here, below, done, remaining, phase, weight,
                                                 GOLDEN_FRACTION)
    paths = LevelPaths(texels, upper, counts, done, remaining, phase, weight)
    return paths, LevelStarts(volume, geometry, config, iso, ids, high, landing, texels,
                              upper, newton_reach(volume, config))


@dataclass(frozen=True)
class Tracing:
    """What every chunk of a bake traces with, made once per bake.

    Attributes:
        ids: (A,) flat lattice ids of the plan's texels.
        seed_key: ``pcg_hash(seed)``, the start of every path key.
        weights: (C,) weights of the brightness whose second moment the pass sums keep.
        whole: parameters of `integrator.trace_whole_paths` where it covers the bake's
            lighting, else None (`integrator.whole_paths`).
        stratified: the paths' first directions stratified over each texel's samples on
            a level (`kernels.stratify_first_directions`: the traced light of views, and
            bakes whose paths or texels follow the noise or the light, `stratifies`),
            else drawn from the paths' keys as every other dimension (bakes of exactly
            `BakeConfig.samples` paths at every texel).
    """

    ids: np.ndarray
    lighting: TracingLights
    settings: PathSettings
    seed_key: np.uint32
    weights: np.ndarray
    whole: WholePaths | None
    stratified: bool = False


def stratifies(config: BakeConfig) -> bool:
    """Are a bake's first directions stratified (`Tracing.stratified`)? Where its paths
    follow the noise (`BakeConfig.target_error`) or its texels the light
    (`BakeConfig.texel_error`, the default): a bake of exactly `BakeConfig.samples`
    paths at every texel keeps independent directions."""
    return config.target_error is not None or config.texel_error is not None


def trace_chunk(scene: Scene, tracing: Tracing, pos: np.ndarray, samples: np.ndarray,
                start: PathStarts, acc: PassSums, strata: np.ndarray | None = None
                ) -> tuple[int, int, float]:
    """Trace paths (sorted texel positions `pos` (P,), sample indices (P,)) from their start
    points and add the per-texel sums to `acc` (positions index it); `strata` (P,), the
    paths' strata where ``tracing.stratified`` (`kernels.texel_paths`), or None: twice
    their sample indices (a view's texels, of one level each).

    Returns:
        (paths, rays, seconds tracing: inside Embree, or in the compiled call that calls it).
    """
    starts = (tracing.seed_key, tracing.ids, pos, samples, start.texels, start.origins,
              start.normals)
    if not tracing.stratified:
        strata = NO_STRATA
    elif strata is None:
        strata = 2 * np.asarray(samples, np.int64)
    ray_stats = RayStats()
    if tracing.whole is not None and scene.calls is not None:
        trace_whole_paths(scene, tracing.whole, starts, tracing.weights, acc, ray_stats,
                          strata)
    else:
        keys, origins, normals, dirs = kernels.path_starts(*starts)
        if len(strata):
            kernels.stratify_first_directions(tracing.seed_key, tracing.ids, pos, strata,
                                              normals, dirs)
        estimates = trace_paths(scene, origins.T, normals.T, keys, tracing.lighting,
                                tracing.settings, ray_stats, dirs.T)
        kernels.accumulate(pos, estimates, tracing.weights, acc.sum, acc.second, acc.n)
    return len(pos), ray_stats.rays, ray_stats.seconds


def trace_texels(scene: Scene, tracing: Tracing, paths: LevelPaths, lo: int, hi: int,
                 start: LevelStarts) -> tuple[PassSums, int, int, float]:
    """`trace_chunk` of the paths of a level's texels lo … hi − 1 (`chunk_bounds`; `start`
    makes the start points of the level's texels, ``paths.texels``).

    Returns:
        their sums (hi − lo texels, formed from zero), and `trace_chunk`'s counts.
    """
    index, samples, strata = paths.of(lo, hi)
    sums = PassSums(hi - lo, tracing.settings.channels)
    chunk = replace(tracing, ids=tracing.ids[paths.texels[lo:hi]].astype(np.int64, copy=False))
    return sums, *trace_chunk(scene, chunk, index, samples, start.of(lo, hi), sums, strata)


def level_scene(volume: volumes.Volume, iso: float, config: BakeConfig) -> Scene:
    """Embree scene of the level surface ρ = iso (empty at the data's extremes), with the
    seconds its marching cubes took as ``mesh_seconds`` (Embree's as ``build_seconds``).
    The surface is `volumes.tracing_surface`'s: compiled, without the GIL (scikit-image
    held it for 0.17 s a level on the engine CT, stalling the plan and the tracing
    workers beside the build), a watertight indexed mesh with zero-area triangles kept
    (no ray hits them)."""
    from isolume.baking.trace import Scene

    lo, hi = volume.value_range
    began = time.perf_counter()
    if lo < iso < hi:
        vertices, faces = volumes.tracing_surface(volume, iso)
    else:
        vertices, faces = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    mesh_seconds = time.perf_counter() - began
    scene = Scene(vertices, faces)
    scene.mesh_seconds = mesh_seconds
    return scene
