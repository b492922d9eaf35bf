"""Reference images: per-pixel Monte Carlo path tracing of the displayed isosurface.

Every pixel's primary ray (origin and direction arrays: this module knows no camera)
is traced once against the marching-cubes mesh of the displayed isosurface. At the hit
point the pixel's outgoing radiance albedo·E/π is estimated with the baker's own
integrator (`integrator.trace_paths`: next-event estimation, MIS, diffuse bounces), from a
start point prepared like a texel's (`bake.start_points`): the smoothed-gradient normal of
the volume, turned towards the eye, and the origin moved `config.offset` voxels along it.
Lattice and reference therefore estimate the same quantity; they differ only in where it
is evaluated (interpolated from texels, or exactly at the visible point).

Randomness: sample s of pixel p uses the key ``rng.path_keys(seed, p, s)`` (p = flat pixel
index, row-major from the top-left), so the image does not depend on the number of
workers, on how the work was split into jobs, or on interruptions and resumption.

Statistics: per pixel the sample count n, the sum Σx and the centred sum of squares
m2 = Σ(x − x̄)² of the radiance samples x (RGB, float64). Jobs merge by the pairwise
formula of Chan, Golub & LeVeque (1979), which stays exact where the variance vanishes
(a uniform sky on a convex surface), unlike Σx² − n·x̄². The standard error of a pixel is
sqrt(m2 / (n − 1) / n). The state (`PixelStats` plus metadata) lives in an ``.npz`` file,
so a reference can be refined later: more samples, exact statistics.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import volumes

from . import rng
from .bake import make_lighting, path_settings
from .config import BakeConfig
from .errors import BakeError
from .integrator import Lighting, PathSettings, trace_paths
from .lattice import volume_identity

STATE_VERSION = 1
PIXELS_PER_BLOCK = 1024
"""Hit pixels per job (consecutive in scan order, so a block is a band of rows)."""
SAMPLES_PER_PASS = 16
"""Sample indices per pass: a job traces ≤ 1024 × 16 = 16384 paths. The split is fixed
(never derived from the worker count), so every worker count gives the same bits."""


@dataclass
class PixelStats:
    """Running per-pixel statistics of the radiance samples.

    Attributes:
        count: (N,) int64 samples per pixel.
        sum: (N, 3) float64 Σx, linear radiance (RGB).
        m2: (N, 3) float64 Σ(x − mean)², radiance².
    """

    count: np.ndarray
    sum: np.ndarray
    m2: np.ndarray

    @classmethod
    def empty(cls, pixels: int) -> PixelStats:
        """Statistics of `pixels` pixels with no samples."""
        return cls(np.zeros(pixels, np.int64), np.zeros((pixels, 3)), np.zeros((pixels, 3)))

    def merge(self, idx: np.ndarray, count: np.ndarray, sums: np.ndarray,
              m2: np.ndarray) -> None:
        """Add the statistics of a batch: (M,) pixel indices (unique), (M,) counts,
        (M, 3) sums and (M, 3) centred sums of squares (Chan et al.'s pairwise update)."""
        n_a = self.count[idx].astype(np.float64)[:, None]
        n_b = count.astype(np.float64)[:, None]
        n = n_a + n_b
        safe_a, safe_n = np.maximum(n_a, 1), np.maximum(n, 1)
        delta = sums / np.maximum(n_b, 1) - self.sum[idx] / safe_a
        self.m2[idx] += m2 + np.where(n_a > 0, delta * delta * n_a * n_b / safe_n, 0.0)
        self.sum[idx] += sums
        self.count[idx] += count

    def mean(self) -> np.ndarray:
        """(N, 3) mean radiance (0 where there is no sample)."""
        n = np.maximum(self.count, 1)[:, None]
        return np.where(self.count[:, None] > 0, self.sum / n, 0.0)

    def stderr(self) -> np.ndarray:
        """(N, 3) standard error of the mean radiance; inf where fewer than 2 samples."""
        n = self.count.astype(np.float64)[:, None]
        var = self.m2 / np.maximum(n - 1, 1)
        return np.where(n > 1, np.sqrt(np.maximum(var, 0.0) / np.maximum(n, 1)), np.inf)


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


def primary_hits(scene, volume: volumes.Volume, origins: np.ndarray, dirs: np.ndarray,
                 config: BakeConfig, smooth: bool = True) -> PrimaryHits:
    """Trace the (N, 3) primary rays `origins`, `dirs` (unit) against `scene` and prepare
    the first path vertex of each hit pixel like the baker prepares a texel's.

    Args:
        scene: `baking.trace.Scene` of the displayed isosurface.
        smooth: smoothed-gradient normals (the paper's) or plain central differences.
    """
    hits = scene.intersect(origins, dirs)
    pixels = np.flatnonzero(hits["hit"])
    d = np.asarray(dirs, np.float64)[pixels]
    points = np.asarray(origins, np.float64)[pixels] + hits["t"][pixels, None] * d
    normals = volumes.normals_at(volume, points, smooth=smooth,
                                 flip=config.flip_normals).astype(np.float64)
    normals = _to_visible_side(normals, hits["ng"][pixels], d)
    h = float(np.mean(volume.spacing))
    return PrimaryHits(pixels, points, points + config.offset * h * normals, normals)


def _to_visible_side(normals: np.ndarray, facet: np.ndarray, dirs: np.ndarray) -> np.ndarray:
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


def rotated_lighting(lighting: Lighting, rotation: np.ndarray | None) -> Lighting:
    """`lighting` with its environment turned by the (3, 3) `rotation` (None: unchanged)."""
    if rotation is None or lighting.env is None:
        return lighting
    from .environment import rotated

    return dataclasses.replace(lighting, env=rotated(lighting.env, np.asarray(rotation)))


def background(lighting: Lighting, dirs: np.ndarray) -> np.ndarray:
    """(N, 3) radiance seen along (N, 3) rays that miss the surface: the environment's,
    or black without one."""
    if lighting.env is None:
        return np.zeros((len(dirs), 3))
    return np.asarray(lighting.env.radiance(np.asarray(dirs, np.float64)), np.float64)


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


def _plan_jobs(done: np.ndarray, target: int) -> list[_Job]:
    """Jobs that bring hit pixels with `done` (M,) samples to `target`, in commit order.

    Pass k covers sample indices [16k, 16k + 16); within a pass, blocks of 1024 hit pixels
    in scan order. Committing in this order keeps each pixel's sample indices contiguous.
    """
    jobs = []
    if len(done) == 0 or done.min() >= target:
        return jobs
    for lo in range(int(done.min()) // SAMPLES_PER_PASS * SAMPLES_PER_PASS, target,
                    SAMPLES_PER_PASS):
        first = np.maximum(done, lo)
        n = np.maximum(np.minimum(target, lo + SAMPLES_PER_PASS) - first, 0)
        for start in range(0, len(done), PIXELS_PER_BLOCK):
            block = slice(start, start + PIXELS_PER_BLOCK)
            rows = np.arange(start, min(start + PIXELS_PER_BLOCK, len(done)))
            keep = n[block] > 0
            if keep.any():
                jobs.append(_Job(rows[keep], first[block][keep], n[block][keep]))
    return jobs


def _trace_job(scene, hits: PrimaryHits, job: _Job, lighting: Lighting,
               settings: PathSettings, seed: int):
    """Worker: trace one job's paths.

    Returns:
        (rows (K,), count (K,), sums (K, 3), m2 (K, 3), rays, seconds in Embree).
    """
    from .trace import RayStats

    local = np.repeat(np.arange(len(job.rows)), job.n)
    starts = np.repeat(job.first - np.concatenate([[0], np.cumsum(job.n)[:-1]]), job.n)
    samples = starts + np.arange(len(local))
    rows = job.rows[local]
    keys = rng.path_keys(seed, hits.pixels[rows], samples)
    stats = RayStats()
    irradiance = trace_paths(scene, hits.origins[rows], hits.normals[rows], keys, lighting,
                             settings, stats)
    radiance = irradiance * (np.asarray(settings.albedo) / np.pi)
    k = len(job.rows)
    sums = np.stack([np.bincount(local, radiance[:, c], minlength=k) for c in range(3)], 1)
    dev = radiance - (sums / job.n[:, None])[local]
    m2 = np.stack([np.bincount(local, dev[:, c] ** 2, minlength=k) for c in range(3)], 1)
    return job.rows, job.n, sums, m2, stats.rays, stats.seconds


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
    """What this process traced (rays include primary and shadow rays)."""

    rays: int = 0
    embree_seconds: float = 0.0
    paths: int = 0
    started: float = dataclasses.field(default_factory=time.perf_counter)

    @property
    def seconds(self) -> float:
        """Wall seconds since the tracer was made."""
        return time.perf_counter() - self.started


class ReferenceTracer:
    """The displayed isosurface as an Embree scene, its primary hits and a thread pool.

    Args:
        volume: the scalar field.
        iso: the displayed isovalue.
        origins, dirs: (N, 3) primary rays, one per pixel (dirs unit length).
        config: lighting, albedo, bounces, seed, offset, flip_normals (``mode`` must be
            "irradiance"; ``samples`` is the default target per pixel).
        smooth: smoothed-gradient (True) or plain-gradient first-vertex normals.
        env_rotation: (3, 3) rotation R of the environment, L'(ω) = L(Rᵀω) (the renderer's
            ``--env-rotation``, `baking.sh.rotation_from_az_el`), or None.
        workers: tracing threads (default: CPU count); the image does not depend on it.
    """

    def __init__(self, volume: volumes.Volume, iso: float, origins: np.ndarray,
                 dirs: np.ndarray, config: BakeConfig, *, smooth: bool = True,
                 env_rotation: np.ndarray | None = None, workers: int | None = None) -> None:
        from .trace import Scene

        if config.mode != "irradiance":
            raise BakeError("a reference image needs mode 'irradiance' (radiance per pixel)")
        origins, dirs = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
        if origins.shape != dirs.shape or origins.ndim != 2 or origins.shape[1] != 3:
            raise ValueError(f"origins {origins.shape} and dirs {dirs.shape}: expected (N, 3)")
        self.volume, self.iso, self.config, self.smooth = volume, float(iso), config, smooth
        self.counters = TraceCounters()
        self.mesh = volumes.isosurface(volume, iso, normals="smooth" if smooth else "gradient",
                                       flip_normals=config.flip_normals)
        self.scene = Scene(self.mesh.vertices, self.mesh.faces)
        self.lighting = rotated_lighting(make_lighting(config), env_rotation)
        self.settings = path_settings(volume, config)
        self.pixels = len(origins)
        self.hits = primary_hits(self.scene, volume, origins, dirs, config, smooth)
        self.counters.rays += self.pixels
        self.background = background(self.lighting, dirs)
        self.identity = {
            "version": STATE_VERSION, "volume": volume_identity(volume), "iso": self.iso,
            "pixels": self.pixels, "rays": rays_hash(origins, dirs),
            "normals": "smooth" if smooth else "gradient",
            "env_rotation": None if env_rotation is None else np.asarray(env_rotation).tolist(),
            "config": dataclasses.replace(config, samples=1).to_dict(),
        }
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers or os.cpu_count() or 1))

    def pending_paths(self, stats: PixelStats, spp: int) -> int:
        """Paths still to trace to bring every hit pixel to `spp` samples."""
        return int(np.maximum(spp - stats.count[self.hits.pixels], 0).sum())

    def run(self, stats: PixelStats, spp: int | None = None, *, bar=None,
            after_pass=None) -> None:
        """Add samples to `stats` until every hit pixel has `spp` (default
        ``config.samples``).

        Args:
            bar: a tqdm-like progress bar (``update``, ``set_postfix_str``), or None.
            after_pass: called with no arguments after each pass of 16 sample indices (a
                consistent state: save a checkpoint there).

        On KeyboardInterrupt the jobs committed so far stay in `stats` (whole jobs, in
        order, so a later run resumes exactly) and the exception propagates.
        """
        spp = self.config.samples if spp is None else int(spp)
        if spp < 1:
            raise BakeError(f"--spp {spp}: expected at least 1 sample per pixel")
        jobs = _plan_jobs(stats.count[self.hits.pixels], spp)
        futures = [self._pool.submit(_trace_job, self.scene, self.hits, job, self.lighting,
                                     self.settings, self.config.seed) for job in jobs]
        try:
            for i, future in enumerate(futures):
                self._commit(stats, future.result(), bar, spp)
                last_of_pass = i + 1 == len(jobs) or jobs[i + 1].rows[0] <= jobs[i].rows[0]
                if after_pass is not None and last_of_pass:
                    after_pass()
        finally:
            for future in futures:
                future.cancel()

    def _commit(self, stats: PixelStats, result, bar, spp: int) -> None:
        rows, count, sums, m2, rays, seconds = result
        stats.merge(self.hits.pixels[rows], count, sums, m2)
        self.counters.rays += rays
        self.counters.embree_seconds += seconds
        self.counters.paths += int(count.sum())
        if bar is not None:
            bar.update(int(count.sum()))
            done = int(stats.count[self.hits.pixels].min()) if len(self.hits.pixels) else spp
            rate = self.counters.rays / max(self.counters.seconds, 1e-9) / 1e6
            bar.set_postfix_str(f"spp {done}/{spp} {rate:.2f} Mrays/s", refresh=False)

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

    def __exit__(self, *exc) -> None:
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
def save_state(path: str | os.PathLike, stats: PixelStats, meta: dict) -> None:
    """Write `stats` and JSON-ready `meta` atomically to `path` (.npz)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, count=stats.count, sum=stats.sum, m2=stats.m2,
                                meta=np.array(json.dumps(meta)))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_state(path: str | os.PathLike) -> tuple[PixelStats, dict]:
    """Read a state file written by `save_state`.

    Raises:
        BakeError: unreadable file or another format version.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            stats = PixelStats(z["count"].astype(np.int64), z["sum"], z["m2"])
            meta = json.loads(str(z["meta"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
        raise BakeError(f"{path}: not a readable isolume reference state ({exc})") from None
    if meta.get("identity", {}).get("version") != STATE_VERSION:
        raise BakeError(f"{path}: reference state of another format version; delete it")
    return stats, meta
