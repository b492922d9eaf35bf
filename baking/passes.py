"""The pieces of a bake's pass that every tracing backend shares (`baking.backend`).

A pass brings some texels up to a sample count. On each isovalue level, the texels that
bracket it trace their pending paths (`lay_out_level`: positions, sample indices and start
points) on the level's scene (`level_scene`), in chunks of whole texels (`chunk_bounds`,
`trace_chunk`); the per-texel sums go to the pass sums (`PassSums`), and a texel complete
on its upper level is merged into the lattice (`commit_sums`). A texel's paths and start
point depend on that texel alone and its sums are added in sample order, so the lattice
is the same bits whoever traces the chunks. A texel's facing (`landing_facing`, committed
by `commit_facing`) comes from the plan alone, so it is the same bits too.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.baking import kernels, octahedral
from isolume.baking.config import BakeConfig
from isolume.baking.integrator import (
    PathSettings,
    TracingLights,
    WholePaths,
    trace_paths,
    trace_whole_paths,
)
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.plan import GOLDEN_FRACTION, Plan, newton_reach, project_to_level
from isolume.baking.rays import RayStats

if TYPE_CHECKING:  # embreex is imported only when a bake runs
    from isolume.baking.trace import Scene

PATHS_PER_CHUNK = 16384
MIN_PATHS_PER_CHUNK = 2048


class PassSums:
    """Per-texel sums of one pass over some texels (float64): ``sum`` (A, C), ``second``
    (A,) (squared brightness) and ``n`` (A,) (paths)."""

    def __init__(self, count: int, channels: int) -> None:
        self.sum = np.zeros((count, channels))
        self.second = np.zeros(count)
        self.n = np.zeros(count, np.int64)

    def clear(self, positions: np.ndarray) -> None:
        self.sum[positions] = 0
        self.second[positions] = 0
        self.n[positions] = 0


def commit_sums(lattice: Lattice, plan: Plan, acc: PassSums, positions: np.ndarray) -> int:
    """Merge the pass sums of texels `positions` (plan positions) into the lattice's running
    means (`kernels.commit_means`: compiled, and the GIL stays free for the tracing
    threads).

    Returns:
        how many of them had no sample before.
    """
    return kernels.commit_means(plan.ids, np.asarray(positions, np.int64),
                                lattice.values.reshape(-1, lattice.values.shape[-1]),
                                lattice.samples.reshape(-1), lattice.second.reshape(-1),
                                acc.sum, acc.second, acc.n)


def landing_facing(volume: volumes.Volume, config: BakeConfig, plan: Plan,
                   positions: np.ndarray) -> np.ndarray:
    """(P, 2) uint8 facings (`baking.octahedral`) of the texels at the (P,) plan
    `positions`: the mean of their start normals on their two levels (`start_points`'
    normals at `Plan.landing`), weighted like their samples (1 − weight, weight); unknown
    where that mean vanishes."""
    positions = np.asarray(positions, np.int64)
    share = np.stack([1 - plan.weight[positions], plan.weight[positions]], axis=1)
    mean = np.zeros((len(positions), 3))
    for side in (0, 1):
        used = share[:, side] > 0
        if used.any():
            normals = lit_normals(volume, config, plan.landing[positions[used], side],
                                  plan.high[positions[used]])
            mean[used] += share[used, side, None] * normals
    return octahedral.encode(mean)


def lit_normals(volume: volumes.Volume, config: BakeConfig, points: np.ndarray,
                high: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit normals at (N, 3) world points on a level, towards each point's
    lit side: lower values, higher where `high` (N,) bool (`Plan.high`)."""
    normals = volumes.normals_at(volume, points,
                                 smooth=config.normals == "smooth").astype(np.float64)
    return np.where(np.asarray(high, bool)[:, None], -normals, normals)


def commit_facing(lattice: Lattice, volume: volumes.Volume, config: BakeConfig, plan: Plan,
                  positions: np.ndarray) -> None:
    """Set the facings (`landing_facing`) of the texels at plan `positions` about to be
    committed that have none yet, or no samples yet (a texel reset by another plan)."""
    flat = plan.ids[positions]
    codes = lattice.facing.reshape(-1, 2)
    todo = ~octahedral.known(codes[flat]) | (lattice.samples.reshape(-1)[flat] == 0)
    if todo.any():
        codes[flat[todo]] = landing_facing(volume, config, plan, positions[todo])


def chunk_bounds(pos: np.ndarray, workers: int):
    """(lo, hi) slices of the sorted path array `pos`, cut only where the texel changes (a
    texel's paths stay in one chunk, so its sum is added in sample order whatever the
    number of workers).

    Guided sizes: each chunk takes 1/(2·workers) of the paths left, between
    MIN_PATHS_PER_CHUNK and PATHS_PER_CHUNK, so a level ends with small chunks and no
    worker waits long for the last one.
    """
    lo, n = 0, len(pos)
    while lo < n:
        size = min(PATHS_PER_CHUNK, max(MIN_PATHS_PER_CHUNK, (n - lo) // (2 * workers)))
        hi = min(lo + size, n)
        if hi < n:  # extend to the end of the texel at the cut
            hi = int(np.searchsorted(pos, pos[hi - 1], side="right"))
        yield lo, hi
        lo = hi


def start_points(volume: volumes.Volume, centres: np.ndarray, level: float,
                 config: BakeConfig, high: np.ndarray, on_level: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Texel centres (N, 3) moved onto a level surface (at most the plan's `newton_reach`)
    and offset along the normal of their lit side (`high` (N,): `Plan.high`). `on_level`
    (N, 3): where that move lands, when the plan already projected them (`Plan.landing`:
    the same computation).

    Returns:
        origins (N, 3) world, normals (N, 3) unit (high → low values, low → high where
        `high`).
    """
    h = float(np.mean(volume.spacing))
    if on_level is None:
        on_level = project_to_level(volume, centres, level,
                                    max_move=newton_reach(volume, config))
    normals = lit_normals(volume, config, on_level, high)
    return on_level + config.offset * h * normals, normals


@dataclass(frozen=True)
class PathStarts:
    """Where the paths of one level start: per texel, sorted by texel position.

    Attributes:
        texels: (T,) sorted texel positions (indices into the plan).
        origins: (T, 3) float32 start points (world), normals: (T, 3) float32 unit.
    """

    texels: np.ndarray
    origins: np.ndarray
    normals: np.ndarray


def lay_out_level(volume: volumes.Volume, geometry: LatticeGeometry, config: BakeConfig,
                  iso: float, ids: np.ndarray, phase: np.ndarray, weight: np.ndarray,
                  high: np.ndarray, here: np.ndarray, below: np.ndarray, done: np.ndarray,
                  remaining: np.ndarray, landing: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, PathStarts]:
    """The pending paths of the level surface ρ = `iso` and their texels' start points
    (a local bake lays out whole levels with it, a cluster task its own texels). Each
    texel's paths and start point depend on that texel alone.

    Args:
        ids, phase, weight, high: (T,) the plan's lattice ids, level phases, upper
            weights and lit sides, of all its texels or of any subset (positions then
            index the subset).
        here, below, done, remaining: as `kernels.level_paths` (positions into `ids`).
        landing: (T, 2, 3) the plan's `Plan.landing` of the same texels, or None to
            project them here (cluster tasks, which are not sent it).

    Returns:
        positions (P,) and sample indices (P,) of the paths, sorted by position, and
        their `PathStarts`.
    """
    pos, samples, texels = kernels.level_paths(here, below, done, remaining, phase, weight,
                                               GOLDEN_FRACTION)
    on_level = None
    if landing is not None:  # the texels of `here` land on their lower level, `below` upper
        on_level = landing[texels, np.isin(texels, below).astype(np.int64)]
    origins, normals = start_points(volume, geometry.centres(ids[texels]), iso, config,
                                    high[texels], on_level)
    return pos, samples, PathStarts(texels, origins.astype(np.float32),
                                    normals.astype(np.float32))


@dataclass(frozen=True)
class Tracing:
    """What every chunk of a bake traces with, made once per bake.

    Attributes:
        ids: (A,) flat lattice ids of the plan's texels.
        seed_key: ``pcg_hash(seed)``, the start of every path key.
        weights: (C,) weights of the brightness whose second moment the pass sums keep.
        acc: the pass sums the chunks add to.
        whole: parameters of `integrator.trace_whole_paths` where it covers the bake's
            lighting, else None (`integrator.whole_paths`).
    """

    ids: np.ndarray
    lighting: TracingLights
    settings: PathSettings
    seed_key: np.uint32
    weights: np.ndarray
    acc: PassSums
    whole: WholePaths | None


def trace_chunk(scene: Scene, tracing: Tracing, pos: np.ndarray, samples: np.ndarray,
                start: PathStarts) -> tuple[int, int, float]:
    """Trace paths (sorted texel positions `pos` (P,), sample indices (P,)) from their start
    points and add the per-texel sums to the pass sums.

    Returns:
        (paths, rays, seconds tracing: inside Embree, or in the compiled call that calls it).
    """
    starts = (tracing.seed_key, tracing.ids, pos, samples, start.texels, start.origins,
              start.normals)
    ray_stats = RayStats()
    acc = tracing.acc
    if tracing.whole is not None and scene.calls is not None:
        trace_whole_paths(scene, tracing.whole, starts, tracing.weights, acc, ray_stats)
    else:
        keys, origins, normals, dirs = kernels.path_starts(*starts)
        estimates = trace_paths(scene, origins.T, normals.T, keys, tracing.lighting,
                                tracing.settings, ray_stats, dirs.T)
        kernels.accumulate(pos, estimates, tracing.weights, acc.sum, acc.second, acc.n)
    return len(pos), ray_stats.rays, ray_stats.seconds


def level_scene(volume: volumes.Volume, iso: float, config: BakeConfig) -> Scene:
    """Embree scene of the level surface ρ = iso (empty at the data's extremes), with the
    seconds its marching cubes took as ``mesh_seconds`` (Embree's as ``build_seconds``).
    The surface is `volumes.tracing_surface`'s: compiled, without the GIL (scikit-image
    held it for 0.17 s a level on the engine CT, stalling the plan and the tracing
    workers beside the build), a watertight triangle soup with zero-area triangles kept
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
