"""The baker: fills a lattice by path tracing, level by level, on worker threads.

Order of work: for each isovalue level (one marching-cubes mesh and one Embree scene alive
at a time), the texels that bracket it trace the paths assigned to it, in chunks of whole
texels on a thread pool. A texel's pass is complete once its upper level is done; complete
texels are committed to the lattice (running means and sample counts), which is saved
atomically at checkpoints, at the end, and on Ctrl-C — finished work is never lost, and
running the same bake again resumes where it stopped.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import volumes

from . import rng
from .config import BakeConfig
from .errors import BakeError
from .integrator import Lighting, PathSettings, trace_paths
from .lattice import LUMINANCE, Lattice, LatticeGeometry, volume_identity
from .lights import parse_light
from .plan import Plan, make_plan, project_to_level

PATHS_PER_CHUNK = 16384


@dataclass
class BakeStats:
    """Counters reported in the lattice metadata and on the progress bar."""

    rays: int = 0
    trace_seconds: float = 0.0
    scene_seconds: float = 0.0
    paths: int = 0
    started: float = field(default_factory=time.perf_counter)

    def add_rays(self, rays: int, seconds: float) -> None:
        self.rays += rays
        self.trace_seconds += seconds


def make_lighting(config: BakeConfig) -> Lighting:
    """Parse the environment and lights of `config`."""
    from .environment import ConstantEnvironment, parse_env

    env = parse_env(config.env) if config.env else None
    sample_env = env is not None and not isinstance(env, ConstantEnvironment)
    return Lighting(env, sample_env, tuple(parse_light(s) for s in config.lights))


def path_settings(volume: volumes.Volume, config: BakeConfig) -> PathSettings:
    """Integrator parameters for `config` on `volume`."""
    h = float(min(volume.spacing))
    return PathSettings(
        bounces=config.bounces, albedo=config.albedo, hit_offset=2e-3 * h,
        sh_order=config.sh_order if config.mode == "sh" else None,
        rgb_transfer=config.mode == "sh" and not config.gray,
    )


def start_points(volume: volumes.Volume, centres: np.ndarray, level: float,
                 config: BakeConfig) -> tuple[np.ndarray, np.ndarray]:
    """Texel centres moved onto a level surface and offset along the normal.

    Returns:
        origins (N, 3) world, normals (N, 3) unit (high → low values unless flipped).
    """
    h = float(np.mean(volume.spacing))
    on_level = project_to_level(volume, centres, level, max_move=4 * config.max_move * h)
    normals = volumes.normals_at(volume, on_level, flip=config.flip_normals).astype(np.float64)
    return on_level + config.offset * h * normals, normals


class _Accumulator:
    """Per-texel sums of one pass over the active texels (float64)."""

    def __init__(self, count: int, channels: int) -> None:
        self.sum = np.zeros((count, channels))
        self.second = np.zeros(count)
        self.n = np.zeros(count, np.int64)

    def add(self, positions: np.ndarray, sums: np.ndarray, second: np.ndarray,
            n: np.ndarray) -> None:
        self.sum[positions] += sums
        self.second[positions] += second
        self.n[positions] += n


def _commit(lattice: Lattice, plan: Plan, acc: _Accumulator, positions: np.ndarray) -> None:
    """Merge the pass sums of texels `positions` into the lattice's running means."""
    positions = positions[acc.n[positions] > 0]
    if len(positions) == 0:
        return
    flat = plan.ids[positions]
    values = lattice.values.reshape(-1, lattice.values.shape[-1])
    samples = lattice.samples.reshape(-1)
    second = lattice.second.reshape(-1)
    old = samples[flat].astype(np.float64)
    new = old + acc.n[positions]
    values[flat] = ((values[flat] * old[:, None] + acc.sum[positions]) / new[:, None])
    second[flat] = (second[flat] * old + acc.second[positions]) / new
    samples[flat] = new.astype(np.uint32)
    acc.sum[positions] = 0
    acc.second[positions] = 0
    acc.n[positions] = 0


def _luminance(estimates: np.ndarray, irradiance: bool) -> np.ndarray:
    return estimates[:, :3] @ LUMINANCE if irradiance else estimates[:, 0]


def _chunks(positions: np.ndarray, remaining: np.ndarray):
    """Split texel positions into runs of whole texels with about PATHS_PER_CHUNK paths."""
    cum = np.cumsum(remaining)
    start = 0
    while start < len(positions):
        base = cum[start - 1] if start else 0
        stop = int(np.searchsorted(cum, base + PATHS_PER_CHUNK, side="right"))
        stop = max(stop, start + 1)
        yield positions[start:stop]
        start = stop


def _load_or_create(volume: volumes.Volume, config: BakeConfig, geometry: LatticeGeometry,
                    out: Path | None, channels: int) -> Lattice:
    """Resume from `out` when it holds a compatible lattice, else start empty."""
    meta = {"kind": config.mode, "sh_order": config.sh_order if config.mode == "sh" else None,
            "scale": config.scale, "volume": volume_identity(volume),
            "config": config.to_dict(), "channels": channels}
    if out is None or not out.exists():
        return Lattice.empty(geometry, channels, meta)
    lattice = Lattice.load(out, volume)
    previous = BakeConfig.from_dict(lattice.meta["config"])
    if not previous.same_result_as(config):
        raise BakeError(f"{out}: holds a bake with other settings ({previous}); to resume, "
                        "repeat them, or write to a new --out file")
    lattice.meta.update(meta)
    return lattice


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="path", unit_scale=True, disable=not enabled,
                dynamic_ncols=True, smoothing=0.1, desc="baking")


def bake(volume: volumes.Volume, config: BakeConfig, *, out: str | os.PathLike | None = None,
         workers: int | None = None, progress: bool = False,
         checkpoint_seconds: float = 60.0) -> Lattice:
    """Bake (or resume) the illumination lattice of `volume` for `config`.

    Args:
        out: lattice file; if it exists with the same volume and settings, the bake
            resumes and brings every active texel up to `config.samples` paths.
        workers: threads tracing concurrently (default: CPU count). The result does not
            depend on it.
        progress: show a progress bar on stderr.
        checkpoint_seconds: save finished texels to `out` at least this often.

    Returns:
        The lattice (also written to `out`).
    """
    out = Path(out) if out is not None else None
    workers = max(1, workers or os.cpu_count() or 1)
    settings = path_settings(volume, config)
    geometry = LatticeGeometry.for_volume(volume, config.scale)
    lattice = _load_or_create(volume, config, geometry, out, settings.channels)
    lighting = make_lighting(config)
    plan = make_plan(volume, geometry, config)
    lattice.active = plan.active
    done = lattice.samples.reshape(-1)[plan.ids].astype(np.int64)
    remaining = np.maximum(config.samples - done, 0)
    stats = BakeStats()
    acc = _Accumulator(len(plan.ids), settings.channels)
    bar = _progress(int(remaining.sum()), progress)
    last_save = time.perf_counter()
    previous = lattice.meta.get("stats", {})
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        for level in range(len(plan.levels)):
            _bake_level(volume, config, plan, level, done, remaining, lighting, settings,
                        pool, acc, stats, bar)
            # a texel's pass is complete once its upper level is done
            _commit(lattice, plan, acc, np.flatnonzero(plan.lower + 1 <= level))
            if out is not None and time.perf_counter() - last_save > checkpoint_seconds:
                _finish_meta(lattice, plan, stats, previous)
                lattice.save(out)
                last_save = time.perf_counter()
        _commit(lattice, plan, acc, np.arange(len(plan.ids)))
    except KeyboardInterrupt:
        # Texels committed so far are kept; the cut pass of the others is dropped whole.
        pool.shutdown(wait=True, cancel_futures=True)
        if out is not None:
            _finish_meta(lattice, plan, stats, previous)
            lattice.save(out)
        raise
    finally:
        pool.shutdown(wait=True)
        bar.close()
    _finish_meta(lattice, plan, stats, previous)
    if out is not None:
        lattice.save(out)
    return lattice


def _bake_level(volume, config, plan, level, done, remaining, lighting, settings, pool, acc,
                stats, bar) -> None:
    """Trace every path assigned to isovalue level `level`."""
    involved = np.flatnonzero(((plan.lower == level) | (plan.lower + 1 == level))
                              & (remaining > 0))
    if len(involved) == 0:
        return
    counts = _paths_on_level(plan, involved, done, remaining, level)
    involved, counts = involved[counts > 0], counts[counts > 0]
    if len(involved) == 0:
        return
    iso = float(plan.levels[level])
    t0 = time.perf_counter()
    scene = _level_scene(volume, iso, config)
    origins, normals = start_points(volume, plan_centres(plan, volume, config, involved),
                                    iso, config)
    stats.scene_seconds += time.perf_counter() - t0
    jobs = []
    for chunk in _chunks(involved, counts):
        rows = np.searchsorted(involved, chunk)
        jobs.append(pool.submit(_trace_chunk, scene, plan, chunk, origins[rows],
                                normals[rows], done, remaining, level, lighting, settings,
                                config.seed))
    for job in jobs:
        positions, sums, second, n, rays, seconds = job.result()
        acc.add(positions, sums, second, n)
        stats.add_rays(rays, seconds)
        stats.paths += int(n.sum())
        bar.update(int(n.sum()))
        elapsed = time.perf_counter() - stats.started
        bar.set_postfix_str(f"level {level + 1}/{len(plan.levels)} "
                            f"{stats.rays / max(elapsed, 1e-9) / 1e6:.2f} Mrays/s", refresh=False)


def plan_centres(plan: Plan, volume, config, positions: np.ndarray) -> np.ndarray:
    """(N, 3) world centres of the texels at `positions` in the plan."""
    geometry = LatticeGeometry.for_volume(volume, config.scale)
    return geometry.centres(plan.ids[positions])


def _paths_on_level(plan: Plan, positions: np.ndarray, done, remaining, level) -> np.ndarray:
    """(N,) number of pending samples of each texel that fall on `level`."""
    pos, samples = _pending_samples(positions, done, remaining)
    on = plan.level_of(pos, samples) == level
    return np.bincount(np.searchsorted(positions, pos[on]), minlength=len(positions))


def _pending_samples(positions, done, remaining) -> tuple[np.ndarray, np.ndarray]:
    """Repeat each texel position for its pending sample indices [done, done + remaining)."""
    reps = remaining[positions]
    pos = np.repeat(positions, reps)
    starts = np.repeat(done[positions] - np.concatenate([[0], np.cumsum(reps)[:-1]]), reps)
    return pos, starts + np.arange(len(pos))


def _trace_chunk(scene, plan, chunk, origins, normals, done, remaining, level, lighting,
                 settings, seed):
    """Worker: trace the pending paths of texels `chunk` on `level`; per-texel sums."""
    from .trace import RayStats

    pos, samples = _pending_samples(chunk, done, remaining)
    keep = plan.level_of(pos, samples) == level
    pos, samples = pos[keep], samples[keep]
    local = np.searchsorted(chunk, pos)
    keys = rng.path_keys(seed, plan.ids[pos], samples)
    ray_stats = RayStats()
    estimates = trace_paths(scene, origins[local], normals[local], keys, lighting, settings,
                            ray_stats)
    lum = _luminance(estimates, settings.sh_order is None)
    size = len(chunk)
    sums = np.stack([np.bincount(local, estimates[:, c], minlength=size)
                     for c in range(estimates.shape[1])], axis=1)
    second = np.bincount(local, lum * lum, minlength=size)
    n = np.bincount(local, minlength=size)
    return chunk, sums, second, n, ray_stats.rays, ray_stats.seconds


def _level_scene(volume: volumes.Volume, iso: float, config: BakeConfig):
    """Embree scene of the level surface ρ = iso (empty at the data's extremes)."""
    from .trace import Scene

    lo, hi = volume.value_range
    iso = min(max(iso, lo), hi)
    mesh = volumes.isosurface(volume, iso, flip_normals=config.flip_normals)
    return Scene(mesh.vertices, mesh.faces, mesh.normals)


def _finish_meta(lattice: Lattice, plan: Plan, stats: BakeStats, previous: dict) -> None:
    """Record what the bake did (adding to the counts of earlier runs on the same file)."""
    lattice.meta["rays_traced"] = int(previous.get("rays_traced", 0)) + stats.rays
    lattice.meta["trace_seconds"] = float(previous.get("trace_seconds", 0.0)) + stats.trace_seconds
    wall = time.perf_counter() - stats.started
    lattice.meta["stats"] = {
        "rays_traced": lattice.meta["rays_traced"],
        "trace_seconds": lattice.meta["trace_seconds"],
        "bake_seconds": float(previous.get("bake_seconds", 0.0)) + wall,
        "scene_seconds": float(previous.get("scene_seconds", 0.0)) + stats.scene_seconds,
        "paths": int(previous.get("paths", 0)) + stats.paths,
    }
    lattice.meta["plan"] = {
        "active_texels": len(plan.ids),
        "unreachable_texels": plan.unreachable,
        "total_texels": int(math.prod(lattice.geometry.shape)),
        "levels": [float(v) for v in plan.levels],
        "noise_sigma": plan.noise,
        "move_voxels_p50": float(np.percentile(plan.move_voxels, 50)),
        "move_voxels_p90": float(np.percentile(plan.move_voxels, 90)),
        "move_voxels_max": float(plan.move_voxels.max()),
    }
