"""Reference images: per-pixel Monte Carlo path tracing of the displayed isosurface.

Every pixel's primary ray (origin and direction arrays: this module knows no camera)
is traced once against the marching-cubes mesh of the displayed isosurface. At the hit
point the pixel's outgoing radiance albedo·E/π is estimated with the baker's own
integrator (`integrator.trace_paths`: next-event estimation, MIS, diffuse bounces), from a
start point prepared like a texel's (`bake.start_points`): the smoothed-gradient normal of
the volume, turned towards the eye (to the side of the hit triangle the ray comes from),
and the origin moved `config.offset` voxels along it.
Lattice and reference therefore estimate the same quantity; they differ only in where it
is evaluated (interpolated from texels, or exactly at the visible point).

Randomness: sample s of pixel p uses the key ``rng.path_keys(seed, p, s)`` (p = flat pixel
index, row-major from the top-left), so the image does not depend on the number of
workers, on how the work was split into jobs, or on interruptions and resumption.

Statistics (`PixelStats`): per pixel the sample count and the sums of the radiance
samples and of their squares (RGB, float64), taken about the pixel's first sample so that
the standard error sqrt(m2 / (n − 1) / n) stays exact where the variance is zero. The
state lives in an ``.npz`` file, so a reference can be refined later with exact
statistics.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import threading
import time
import zipfile
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.baking import rng
from isolume.baking.bake import path_settings, tracing_lights
from isolume.baking.config import BakeConfig
from isolume.baking.errors import BakeError
from isolume.baking.integrator import PathSettings, RayStats, TracingLights, trace_paths
from isolume.baking.lattice import volume_identity
from isolume.volumes import cores
from isolume.volumes.writing import atomic_write

if TYPE_CHECKING:
    from isolume.baking.trace import Scene

STATE_VERSION = 1
PIXELS_PER_BLOCK = 1024
"""Hit pixels per job (consecutive in scan order, so a block is a band of rows)."""
SAMPLES_PER_PASS = 16
"""Sample indices per pass: a job traces ≤ 1024 × 16 = 16384 paths. The split is fixed
(never derived from the worker count), so every worker count gives the same bits."""


@dataclass
class PixelStats:
    """Running per-pixel sums of the radiance samples, about a per-pixel shift.

    Sums about a shift c (the pixel's first sample) keep the variance accurate, Σ(x − c)²
    − (Σ(x − c))²/n, and exactly 0 where every sample is equal (a uniform sky on a convex
    surface), which plain Σx² − n·x̄² would bury in rounding noise. Batches merge by
    moving their sums to the stored shift, so adding samples later keeps them exact.

    Attributes:
        count: (N,) int64 samples per pixel.
        shift: (N, 3) float64 c, linear radiance (RGB).
        s1: (N, 3) float64 Σ(x − c).
        s2: (N, 3) float64 Σ(x − c)², radiance².
    """

    count: np.ndarray
    shift: np.ndarray
    s1: np.ndarray
    s2: np.ndarray

    @classmethod
    def empty(cls, pixels: int) -> PixelStats:
        """Statistics of `pixels` pixels with no samples."""
        return cls(np.zeros(pixels, np.int64), *(np.zeros((pixels, 3)) for _ in range(3)))

    def merge(self, idx: np.ndarray, count: np.ndarray, shift: np.ndarray, s1: np.ndarray,
              s2: np.ndarray) -> None:
        """Add a batch: (M,) unique pixel indices, (M,) counts, and its (M, 3) shift and
        sums about it."""
        fresh = self.count[idx] == 0
        self.shift[idx[fresh]] = shift[fresh]
        d = shift - self.shift[idx]  # move the batch's sums to the stored shift
        n = count.astype(np.float64)[:, None]
        self.s2[idx] += s2 + 2 * d * s1 + n * d * d
        self.s1[idx] += s1 + n * d
        self.count[idx] += count

    def mean(self) -> np.ndarray:
        """(N, 3) mean radiance (0 where there is no sample)."""
        n = np.maximum(self.count, 1)[:, None]
        return np.where(self.count[:, None] > 0, self.shift + self.s1 / n, 0.0)

    def stderr(self) -> np.ndarray:
        """(N, 3) standard error of the mean radiance; inf where fewer than 2 samples."""
        n = self.count.astype(np.float64)[:, None]
        m2 = np.maximum(self.s2 - self.s1 * self.s1 / np.maximum(n, 1), 0.0)
        return np.where(n > 1, np.sqrt(m2 / np.maximum(n - 1, 1) / np.maximum(n, 1)), np.inf)


@dataclass(frozen=True)
class PrimaryHits:
    """Where the primary rays meet the isosurface, and the paths' start points there.

    Attributes:
        pixels: (M,) int64 flat indices of the pixels whose ray hits the surface.
        points: (M, 3) world hit points (on the mesh).
        origins: (M, 3) path start points: `points` moved `offset` voxels along `normals`.
        normals: (M, 3) unit smoothed-gradient normals, turned towards the eye.
    """

    pixels: np.ndarray
    points: np.ndarray
    origins: np.ndarray
    normals: np.ndarray


PRIMARY_BLOCK = 1 << 14
"""Primary rays one work item of `primary_hits` traces and prepares."""


def primary_hits(scene: Scene, volume: volumes.Volume, origins: np.ndarray, dirs: np.ndarray,
                 config: BakeConfig, smooth: bool = True) -> PrimaryHits:
    """Trace the (N, 3) primary rays `origins`, `dirs` (unit) against `scene` and prepare
    the first path vertex of each hit pixel like the baker prepares a texel's, a block of
    `PRIMARY_BLOCK` rays an item on every core (each ray's answer is its own: the same
    bits on any number of threads): one compiled call a block where the scene has
    Embree's per-ray calls (`baking.pixel_kernels.primary_starts`), else numpy over
    embreex's batches, to the bit.

    Args:
        scene: `baking.trace.Scene` of the displayed isosurface.
        smooth: smoothed-gradient normals (the paper's) or plain central differences.
    """
    if scene.calls is not None:
        return _compiled_hits(scene, volume, origins, dirs, config, smooth)
    parts = cores.blocks(len(dirs), PRIMARY_BLOCK)
    if len(parts) <= 1:
        return _primary_hits(scene, volume, origins, dirs, config, smooth)
    found: list[PrimaryHits | None] = [None] * len(parts)

    def block(b: int) -> None:
        part = parts[b]
        hits = _primary_hits(scene, volume, origins[part], dirs[part], config, smooth)
        found[b] = dataclasses.replace(hits, pixels=hits.pixels + part.start)

    cores.for_items(block, len(parts), "primary rays")
    return _joined(found)


def _joined(blocks: list[PrimaryHits | None]) -> PrimaryHits:
    """The `PrimaryHits` of consecutive blocks of rays, in their order."""
    return PrimaryHits(*(np.concatenate([getattr(hits, field.name) for hits in blocks])
                         for field in dataclasses.fields(PrimaryHits)))


def _compiled_hits(scene: Scene, volume: volumes.Volume, origins: np.ndarray,
                   dirs: np.ndarray, config: BakeConfig, smooth: bool) -> PrimaryHits:
    """`primary_hits` in compiled blocks (`baking.pixel_kernels.primary_starts`): each
    block's item keeps the hits of its rays, and the blocks' hits are joined in order at
    the end (`_joined`)."""
    from isolume.baking.pixel_kernels import primary_starts
    from isolume.volumes.field import normal_stencil

    stencil = normal_stencil(volume, smooth)
    h = float(np.mean(volume.spacing))
    calls = tuple(scene.calls)
    parts = cores.blocks(len(dirs), PRIMARY_BLOCK)
    if not parts:
        return PrimaryHits(np.zeros(0, np.int64), *(np.zeros((0, 3)) for _ in range(3)))
    found: list[PrimaryHits | None] = [None] * len(parts)

    def block(b: int) -> None:
        part = parts[b]
        count = part.stop - part.start
        hit = np.zeros(count, bool)
        points, starts, normals = (np.empty((count, 3)) for _ in range(3))
        primary_starts(calls, np.ascontiguousarray(origins[part], np.float64),
                       np.ascontiguousarray(dirs[part], np.float64), stencil,
                       bool(config.flip_normals), config.offset * h, 1e-3 * h, hit,
                       points, starts, normals)
        kept = np.flatnonzero(hit)
        found[b] = PrimaryHits(kept + part.start, points[kept], starts[kept], normals[kept])

    cores.for_items(block, len(parts), "primary rays")
    return _joined(found)


def _primary_hits(scene: Scene, volume: volumes.Volume, origins: np.ndarray, dirs: np.ndarray,
                  config: BakeConfig, smooth: bool) -> PrimaryHits:
    """`primary_hits` of one block of rays, on the calling thread."""
    hits = scene.intersect(origins, dirs)
    pixels = np.flatnonzero(hits["prim"] >= 0)
    d = np.asarray(dirs, np.float64)[pixels]
    points = np.asarray(origins, np.float64)[pixels] + hits["t"][pixels, None] * d
    normals = volumes.normals_at(volume, points, smooth=smooth,
                                 flip=config.flip_normals).astype(np.float64)
    normals = to_visible_side(normals, hits["ng"][pixels], d)
    flat = ~(np.abs(np.linalg.norm(normals, axis=1) - 1.0) < 1e-3)  # no gradient (or NaN)
    normals[flat] = -d[flat]  # there the eye's direction is the one side known
    h = float(np.mean(volume.spacing))
    origins = clear_starts(scene, points, points + config.offset * h * normals, d, h)
    return PrimaryHits(pixels, points, origins, normals)


def clear_starts(scene: Scene, points: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                 h: float) -> np.ndarray:
    """(M, 3) path start points checked against the surface they light: a start whose
    step off the surface crosses a facet (a sub-voxel pocket, a fold thinner than the
    offset, where every path would begin inside the material and come back black) moves
    back along its primary ray instead, as far as the offset, which the ray has just
    crossed in free space.

    Args:
        points: (M, 3) hit points on the surface, world units; origins: (M, 3) the
            starts off it; dirs: (M, 3) unit primary ray directions; h: voxel size.
    """
    back = points - 1e-3 * h * dirs  # on the ray, just before the hit: free space
    step = origins - back
    length = np.linalg.norm(step, axis=1)
    out = np.array(origins, np.float64)
    traced = np.flatnonzero(length > 0)  # (Embree's traversal needs finite, non-zero rays)
    if len(traced) == 0:
        return out
    blocked = scene.occluded(back[traced], step[traced] / length[traced, None],
                             tfar=length[traced])
    moved = traced[blocked]
    out[moved] = points[moved] - length[moved, None] * dirs[moved]
    return out


def to_visible_side(normals: np.ndarray, facet: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(M, 3) `normals` turned towards the eye: to the side of the hit facet the ray
    arrives from.

    The facet decides, not the ray: where the smoothed gradient lies nearly in the view
    plane (silhouettes, thin fins whose smoothed gradient leans towards the far face),
    turning it by the sign of n·eye can put it on the wrong side of the facet, and the
    offset origin inside the material, where every path is blocked (black pixels).

    Args:
        normals: (M, 3) unit normals; facet: (M, 3) geometric normals of the hit
            triangles (any length, any winding); dirs: (M, 3) ray directions.
    """
    facet = facet.astype(np.float64)
    facet *= -np.sign((facet * dirs).sum(axis=1, keepdims=True))
    return normals * np.where((normals * facet).sum(axis=1, keepdims=True) < 0, -1.0, 1.0)


def _stopped(stop: threading.Event | None) -> bool:
    """True when `stop` is given and set."""
    return stop is not None and stop.is_set()


def rotated_lighting(lighting: TracingLights, rotation: np.ndarray | None) -> TracingLights:
    """`lighting` with its environment turned by the (3, 3) `rotation` (None: unchanged).
    A procedural sky's compiled parameters describe the unturned sky: they are dropped, so
    the turned one is sampled through its own methods."""
    if rotation is None or lighting.env is None:
        return lighting
    from isolume.baking.environment import rotated

    return dataclasses.replace(lighting, env=rotated(lighting.env, np.asarray(rotation)),
                               sky=None)


def background(lighting: TracingLights, dirs: np.ndarray) -> np.ndarray:
    """(N, 3) radiance seen along (N, 3) rays that miss the surface: the environment's,
    or black without one."""
    if lighting.env is None:
        return np.zeros((len(dirs), 3))
    return np.asarray(lighting.env.radiance(np.asarray(dirs, np.float64)), np.float64)


def _identity_config(config: BakeConfig) -> dict[str, Any]:
    """The configuration a state file is resumed for: every field that changes the
    picture (not ``samples`` and the cap on them, nor ``direct_light``, which a
    reference ignores)."""
    d = dataclasses.replace(config, samples=1, max_samples=BakeConfig.max_samples).to_dict()
    del d["direct_light"]
    return d


def rays_hash(origins: np.ndarray, dirs: np.ndarray) -> str:
    """A digest of the primary rays: a state file is resumed only for the same rays."""
    digest = hashlib.sha1()
    for a in (origins, dirs):
        digest.update(np.ascontiguousarray(a, np.float64).tobytes())
    return digest.hexdigest()


@dataclass(frozen=True)
class _Job:
    """The paths of one job: hit pixels `rows` (indices into `PrimaryHits`), each from
    sample index `first` for `n` samples."""

    rows: np.ndarray
    first: np.ndarray
    n: np.ndarray

    @property
    def paths(self) -> int:
        return int(self.n.sum())


def _plan_jobs(done: np.ndarray, target: int) -> Iterator[tuple[_Job, bool]]:
    """(job, last job of its pass) that bring hit pixels with `done` (M,) samples to
    `target`, in commit order, generated lazily (memory stays bounded at any spp).

    Pass k covers sample indices [16k, 16k + 16); within a pass, blocks of 1024 hit pixels
    in scan order. Committing in this order keeps each pixel's sample indices contiguous.
    """
    if len(done) == 0 or done.min() >= target:
        return
    for lo in range(int(done.min()) // SAMPLES_PER_PASS * SAMPLES_PER_PASS, target,
                    SAMPLES_PER_PASS):
        first = np.maximum(done, lo)
        n = np.maximum(np.minimum(target, lo + SAMPLES_PER_PASS) - first, 0)
        rows = np.flatnonzero(n)
        for start in range(0, len(rows), PIXELS_PER_BLOCK):
            block = rows[start:start + PIXELS_PER_BLOCK]
            yield _Job(block, first[block], n[block]), start + PIXELS_PER_BLOCK >= len(rows)


def pending_samples(positions: np.ndarray, done: np.ndarray, remaining: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Repeat each texel position for its pending sample indices [done, done + remaining)."""
    reps = remaining[positions]
    pos = np.repeat(positions, reps)
    starts = np.repeat(done[positions] - np.concatenate([[0], np.cumsum(reps)[:-1]]), reps)
    return pos, starts + np.arange(len(pos))


def _trace_job(scene, hits: PrimaryHits, job: _Job, lighting: TracingLights,
               settings: PathSettings, seed: int):
    """Worker: trace one job's paths.

    Returns:
        (rows (K,), count (K,), shift, s1, s2 (K, 3) as in `PixelStats`, rays, seconds
        inside Embree).
    """
    local, samples = pending_samples(np.arange(len(job.rows)), job.first, job.n)
    rows = job.rows[local]
    keys = rng.path_keys(seed, hits.pixels[rows], samples)
    stats = RayStats()
    irradiance = trace_paths(scene, hits.origins[rows], hits.normals[rows], keys, lighting,
                             settings, stats)
    radiance = irradiance * (np.asarray(settings.albedo) / np.pi)
    shift, s1, s2 = _moments(radiance, local, job.n)
    return job.rows, job.n, shift, s1, s2, stats.rays, stats.seconds


def _moments(x: np.ndarray, local: np.ndarray, n: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel shift c (first sample), Σ(x − c) and Σ(x − c)² of (P, 3) samples `x` of
    pixels `local` (P,), grouped in order, `n` (K,) samples each. Each (K, 3)."""
    k = len(n)
    shift = x[np.concatenate([[0], np.cumsum(n)[:-1]])]
    d = x - shift[local]
    s1 = np.stack([np.bincount(local, d[:, c], minlength=k) for c in range(3)], 1)
    s2 = np.stack([np.bincount(local, d[:, c] ** 2, minlength=k) for c in range(3)], 1)
    return shift, s1, s2


@dataclass
class ReferenceImage:
    """A reference picture, flat in pixels (reshape to (H, W, ...) with the camera's size).

    Attributes:
        radiance: (N, 3) float64 linear radiance: the mean on the surface, the background
            elsewhere.
        stderr: (N, 3) float64 standard error of `radiance` (0 off the surface, inf on
            surface pixels with fewer than 2 samples).
        mask: (N,) bool, True where the primary ray hits the surface.
    """

    radiance: np.ndarray
    stderr: np.ndarray
    mask: np.ndarray


@dataclass
class TraceCounters:
    """What a tracer did in this process.

    Attributes:
        primary_rays: one per pixel, traced when the tracer is made.
        rays: rays of the paths (continuation and shadow rays) traced by `run`.
        paths: paths traced by `run`.
        setup_seconds: wall time to make the tracer (mesh, Embree scene, primary hits).
        run_seconds: wall time inside `run`.
        embree_seconds: time inside Embree, summed over threads.
    """

    primary_rays: int = 0
    rays: int = 0
    paths: int = 0
    setup_seconds: float = 0.0
    run_seconds: float = 0.0
    embree_seconds: float = 0.0

    @property
    def rays_per_second(self) -> float:
        """Path rays per wall second of `run`."""
        return self.rays / max(self.run_seconds, 1e-9)


class ReferenceTracer:
    """The displayed isosurface as an Embree scene, its primary hits and a thread pool.

    Args:
        volume: the scalar field.
        iso: the displayed isovalue.
        origins, dirs: (N, 3) primary rays, one per pixel (dirs unit length).
        config: lighting, albedo, bounces, seed, offset, flip_normals (``mode`` must be
            "irradiance"; ``samples`` is the default target per pixel; ``direct_light`` is
            ignored: a reference holds all the light).
        smooth: smoothed-gradient (True) or plain-gradient first-vertex normals.
        env_rotation: (3, 3) rotation R of the environment, L'(ω) = L(Rᵀω) (the renderer's
            ``--env-rotation``, `baking.sh.rotation_from_az_el`), or None.
        workers: tracing threads (default: CPU count); the image does not depend on it.
    """

    def __init__(self, volume: volumes.Volume, iso: float, origins: np.ndarray,
                 dirs: np.ndarray, config: BakeConfig, *, smooth: bool = True,
                 env_rotation: np.ndarray | None = None, workers: int | None = None) -> None:
        from isolume.baking.trace import Scene

        if config.mode != "irradiance":
            raise BakeError("a reference image needs mode 'irradiance' (radiance per pixel)")
        origins, dirs = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
        if origins.shape != dirs.shape or origins.ndim != 2 or origins.shape[1] != 3:
            raise ValueError(f"origins {origins.shape} and dirs {dirs.shape}: expected (N, 3)")
        started = time.perf_counter()
        config = dataclasses.replace(config, direct_light="lattice")  # all the light
        self.volume: volumes.Volume = volume
        self.iso: float = float(iso)
        self.config: BakeConfig = config
        self.smooth: bool = smooth
        self.counters: TraceCounters = TraceCounters()
        self.lighting: TracingLights = rotated_lighting(  # bad specs first
            tracing_lights(config), env_rotation)
        self.settings: PathSettings = path_settings(volume, config)
        self.mesh: volumes.Mesh = volumes.isosurface(
            volume, iso, normals="smooth" if smooth else "gradient",
            flip_normals=config.flip_normals)
        self.scene: Scene = Scene(self.mesh.vertices, self.mesh.faces)
        self.pixels: int = len(origins)
        self.hits: PrimaryHits = primary_hits(self.scene, volume, origins, dirs, config, smooth)
        self.counters.primary_rays = self.pixels
        self.background: np.ndarray = background(self.lighting, dirs)
        self.identity: dict[str, Any] = {
            "version": STATE_VERSION, "volume": volume_identity(volume), "iso": self.iso,
            "pixels": self.pixels, "rays": rays_hash(origins, dirs),
            "normals": "smooth" if smooth else "gradient",
            "env_rotation": None if env_rotation is None else np.asarray(env_rotation).tolist(),
            "config": _identity_config(config),
        }
        threads = max(1, workers or cores.threads())
        self._pool = ThreadPoolExecutor(max_workers=threads)
        self._max_in_flight = 2 * threads + 2  # keeps every thread busy, memory bounded
        self.counters.setup_seconds = time.perf_counter() - started

    def holds(self, stats: PixelStats, meta: dict[str, Any]) -> bool:
        """Whether a state file's `stats` and `meta` (`load_state`) are of this tracer's
        volume, isovalue, camera rays and lighting (`identity`), its samples to add to."""
        return meta.get("identity") == self.identity and len(stats.count) == self.pixels

    def pending_paths(self, stats: PixelStats, spp: int) -> int:
        """Paths still to trace to bring every hit pixel to `spp` samples."""
        return int(np.maximum(spp - stats.count[self.hits.pixels], 0).sum())

    def run(self, stats: PixelStats, spp: int | None = None, *, bar: Any = None,
            after_pass: Callable[[], object] | None = None,
            stop: threading.Event | None = None) -> bool:
        """Add samples to `stats` until every hit pixel has `spp` (default
        ``config.samples``).

        Args:
            bar: a tqdm-like progress bar (``update``, ``set_postfix_str``), or None.
            after_pass: called with no arguments after each pass of 16 sample indices (a
                consistent state: save a checkpoint there).
            stop: when set (e.g. by a SIGINT handler), return after the job being
                committed; `stats` then holds whole jobs in order, and a later run
                continues exactly where this one stopped.

        Returns:
            True when every hit pixel has `spp` samples, False when stopped early.
        """
        spp = self.config.samples if spp is None else int(spp)
        if spp < 1:
            raise BakeError(f"--spp {spp}: expected at least 1 sample per pixel")
        in_flight: deque = deque()
        planned_all = True
        started = time.perf_counter()
        try:
            for job, last_of_pass in _plan_jobs(stats.count[self.hits.pixels], spp):
                if _stopped(stop):
                    planned_all = False
                    break
                in_flight.append((self._pool.submit(
                    _trace_job, self.scene, self.hits, job, self.lighting, self.settings,
                    self.config.seed), last_of_pass))
                if len(in_flight) > self._max_in_flight:
                    self._commit(stats, *in_flight.popleft(), bar, spp, started, after_pass)
            while in_flight and not _stopped(stop):
                self._commit(stats, *in_flight.popleft(), bar, spp, started, after_pass)
            return planned_all and not in_flight
        finally:
            for future, _ in in_flight:
                future.cancel()
            self.counters.run_seconds += time.perf_counter() - started

    def _commit(self, stats: PixelStats, future, last_of_pass: bool, bar, spp: int,
                started: float, after_pass) -> None:
        """Merge one job's result into `stats` (main thread, in job order)."""
        rows, count, shift, s1, s2, rays, seconds = future.result()
        stats.merge(self.hits.pixels[rows], count, shift, s1, s2)
        self.counters.rays += rays
        self.counters.embree_seconds += seconds
        self.counters.paths += int(count.sum())
        if bar is not None:
            bar.update(int(count.sum()))
            done = int(stats.count[self.hits.pixels].min())
            elapsed = self.counters.run_seconds + time.perf_counter() - started
            rate = self.counters.rays / max(elapsed, 1e-9) / 1e6
            bar.set_postfix_str(f"spp {done}/{spp} {rate:.2f} Mrays/s", refresh=False)
        if last_of_pass and after_pass is not None:
            after_pass()

    def image(self, stats: PixelStats) -> ReferenceImage:
        """The picture of `stats`: mean radiance on the surface, background elsewhere."""
        mask = np.zeros(self.pixels, bool)
        mask[self.hits.pixels] = True
        radiance = np.where(mask[:, None], stats.mean(), self.background)
        stderr = np.where(mask[:, None], stats.stderr(), 0.0)
        return ReferenceImage(radiance, stderr, mask)

    def close(self) -> None:
        """Stop the worker threads."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ReferenceTracer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def render_reference(volume: volumes.Volume, iso: float, origins: np.ndarray,
                     dirs: np.ndarray, config: BakeConfig, *, smooth: bool = True,
                     env_rotation: np.ndarray | None = None, workers: int | None = None,
                     stats: PixelStats | None = None) -> tuple[ReferenceImage, PixelStats]:
    """One-call reference: `config.samples` samples per hit pixel (added to `stats` when
    given, which is updated in place).

    Returns:
        (image, stats).
    """
    with ReferenceTracer(volume, iso, origins, dirs, config, smooth=smooth,
                         env_rotation=env_rotation, workers=workers) as tracer:
        stats = PixelStats.empty(tracer.pixels) if stats is None else stats
        tracer.run(stats)
        return tracer.image(stats), stats


# -- the state file ---------------------------------------------------------------------
def save_state(path: str | os.PathLike[str], stats: PixelStats, meta: dict[str, Any]) -> None:
    """Write `stats` and JSON-ready `meta` atomically to `path` (.npz)."""
    atomic_write(path, lambda tmp: np.savez_compressed(
        tmp, count=stats.count, shift=stats.shift, s1=stats.s1, s2=stats.s2,
        meta=np.array(json.dumps(meta))))


def load_state(path: str | os.PathLike[str]) -> tuple[PixelStats, dict[str, Any]]:
    """Read a state file written by `save_state`.

    Raises:
        BakeError: unreadable file or another format version.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            stats = PixelStats(z["count"].astype(np.int64), z["shift"], z["s1"], z["s2"])
            meta = json.loads(str(z["meta"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
        raise BakeError(f"{path}: not a readable isolume reference state ({exc})") from None
    if meta.get("identity", {}).get("version") != STATE_VERSION:
        raise BakeError(f"{path}: reference state of another format version; delete it")
    return stats, meta
