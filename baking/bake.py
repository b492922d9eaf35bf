"""The baker: fills a lattice by path tracing, level by level, on worker threads.

Order of work: for each isovalue level (one marching-cubes mesh and one Embree scene alive
at a time), the texels that bracket it trace the paths assigned to it, in chunks of whole
texels on a thread pool. A texel's pass is complete once its upper level is done; complete
texels are committed to the lattice (running means and sample counts), which is saved
atomically at checkpoints, at the end, and on Ctrl-C — finished work is never lost, and
running the same bake again resumes where it stopped.
"""

from __future__ import annotations

import itertools
import math
import os
import sys
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from isolume import volumes
from isolume.baking import kernels, rng
from isolume.baking.config import BakeConfig
from isolume.baking.errors import BakeError
from isolume.baking.integrator import (
    Lighting,
    PathSettings,
    RayStats,
    WholePaths,
    trace_paths,
    trace_whole_paths,
    whole_paths,
)
from isolume.baking.lattice import LUMINANCE, Lattice, LatticeGeometry, volume_identity
from isolume.baking.lights import parse_light
from isolume.baking.plan import (
    GOLDEN_FRACTION,
    Plan,
    make_plan,
    newton_reach,
    project_to_level,
    resolved_iso_range,
)

AHEAD_LEVELS = 2
"""Scenes of the lowest levels a `Baker` builds beside its plan: the helper thread is done
with level 0's before the plan is, and a second scene built then is one fewer built
beside the tracing (engine CT quick bake: 0.2 s of 2.1)."""
PATHS_PER_CHUNK = 16384
MIN_PATHS_PER_CHUNK = 2048
REPORT_S = 0.5
"""Seconds between progress-bar updates while a level is traced."""


@dataclass
class BakeStats:
    """Counters reported in the lattice metadata and on the progress bar."""

    rays: int = 0
    trace_seconds: float = 0.0
    scene_seconds: float = 0.0
    mesh_seconds: float = 0.0
    embree_seconds: float = 0.0
    scenes: int = 0
    paths: int = 0
    started: float = field(default_factory=time.perf_counter)

    def add_rays(self, rays: int, seconds: float) -> None:
        self.rays += rays
        self.trace_seconds += seconds


def make_lighting(config: BakeConfig) -> Lighting:
    """Parse the environment and lights of `config`; the lights' and the sun's direct light
    is left to the renderer when `config.direct_light` is "pixels"."""
    from isolume.baking.environment import ConstantEnvironment, SkyEnvironment, parse_env

    env = parse_env(config.env) if config.env else None
    sample_env = env is not None and not isinstance(env, ConstantEnvironment)
    sky = kernels.sky_params(env) if type(env) is SkyEnvironment else None
    return Lighting(env, sample_env, tuple(parse_light(s) for s in config.lights), sky,
                    pixel_direct=config.direct_light == "pixels")


def path_settings(volume: volumes.Volume, config: BakeConfig) -> PathSettings:
    """Integrator parameters for `config` on `volume`."""
    h = float(min(volume.spacing))
    return PathSettings(
        bounces=config.bounces, albedo=config.albedo, hit_offset=2e-3 * h,
        sh_order=config.sh_order if config.mode == "sh" else None,
        rgb_transfer=config.mode == "sh" and not config.gray,
        # issue 14 part 3: an SH bake with the sun per pixel keeps direct and indirect
        # transfer apart (`baking.integrator` module docs)
        sh_split=config.mode == "sh" and config.direct_light == "pixels",
    )


def start_points(volume: volumes.Volume, centres: np.ndarray, level: float,
                 config: BakeConfig, on_level: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Texel centres moved onto a level surface (at most the plan's `newton_reach`) and
    offset along the normal. `on_level` (N, 3): where that move lands, when the plan
    already projected them (`Plan.landing`: the same computation).

    Returns:
        origins (N, 3) world, normals (N, 3) unit (high → low values unless flipped).
    """
    h = float(np.mean(volume.spacing))
    if on_level is None:
        on_level = project_to_level(volume, centres, level,
                                    max_move=newton_reach(volume, config))
    normals = volumes.normals_at(volume, on_level, smooth=config.normals == "smooth",
                                 flip=config.flip_normals).astype(np.float64)
    return on_level + config.offset * h * normals, normals


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


def _commit(lattice: Lattice, plan: Plan, acc: PassSums, positions: np.ndarray) -> int:
    """Merge the pass sums of texels `positions` into the lattice's running means
    (`kernels.commit_means`: compiled, and the GIL stays free for the tracing threads).

    Returns:
        how many of them had no sample before.
    """
    return kernels.commit_means(plan.ids, np.asarray(positions, np.int64),
                                lattice.values.reshape(-1, lattice.values.shape[-1]),
                                lattice.samples.reshape(-1), lattice.second.reshape(-1),
                                acc.sum, acc.second, acc.n)


def _luminance_weights(channels: int, irradiance: bool, second_block: int = 0) -> np.ndarray:
    """(C,) weights of the brightness whose variance the error estimates use: luminance
    of RGB irradiance, the DC coefficient of SH transfer (of both blocks of a split
    transfer, the second starting at `second_block`: issue 14 part 3)."""
    weights = np.zeros(channels)
    if irradiance:
        weights[:3] = LUMINANCE
    else:
        weights[0] = weights[second_block] = 1.0
    return weights


def _chunk_bounds(pos: np.ndarray, workers: int):
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


def _new_lattice(volume: volumes.Volume, config: BakeConfig, geometry: LatticeGeometry,
                 channels: int) -> Lattice:
    """An empty lattice with the metadata that identifies the volume and the bake."""
    meta = {"kind": config.mode, "sh_order": config.sh_order if config.mode == "sh" else None,
            "scale": config.scale, "volume": volume_identity(volume),
            "config": config.to_dict(), "channels": channels}
    return Lattice.empty(geometry, channels, meta)


def _kept_levels(lattice: Lattice | None) -> np.ndarray | None:
    """(K,) the levels a lattice was started with (a resumed bake keeps them: its samples
    were traced on them), or None."""
    if lattice is None or "plan" not in lattice.meta:
        return None
    return np.asarray(lattice.meta["plan"]["levels"], np.float64)


def _first_level(volume: volumes.Volume, config: BakeConfig,
                 kept: np.ndarray | None) -> float | None:
    """The lowest level the plan will choose, known before it: a resumed bake's first kept
    level, else the bottom of the iso range (`choose_levels` starts there whenever a
    texel's value lies at or below it, as at every surface that crosses it); None when the
    range cannot be resolved (the plan then says why)."""
    if kept is not None:
        return float(kept[0])
    try:
        return float(resolved_iso_range(volume, config)[0])
    except BakeError:
        return None


def _load_existing(volume: volumes.Volume, config: BakeConfig, out: Path | None
                   ) -> Lattice | None:
    """The lattice in `out` when it can be resumed with `config`, None when there is none.

    Raises:
        BakeError: `out` holds a lattice of another volume or other settings.
    """
    if out is None or not out.exists():
        return None
    lattice = Lattice.load(out, volume)
    previous = BakeConfig.from_dict(lattice.meta["config"])
    if not previous.same_result_as(config):
        raise BakeError(f"{out}: holds a bake with other settings ({previous}); to resume, "
                        "repeat them, or write to a new --out file")
    lattice.meta["config"] = config.to_dict()
    return lattice


def _plan_progress(stage: str) -> None:
    """The plan's stages on stderr (a large volume's plan takes seconds)."""
    print(f"planning: {stage}", file=sys.stderr, flush=True)


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="path", unit_scale=True, disable=not enabled,
                dynamic_ncols=True, smoothing=0.1, desc="baking")


class Baker:
    """A lattice being baked: the plan, the lighting, a thread pool and the lattice.

    `run` brings any subset of the active texels up to a sample count, level by level, so
    the same machinery serves a full bake (all texels to `config.samples`) and a lazy,
    progressive one (the texels around the displayed isosurface first, a few samples at a
    time). Level scenes are cached (least recently used first out), which pays off when
    successive runs touch the same few levels.

    Args:
        lattice: an existing lattice to extend (resume); None starts empty.
        workers: threads tracing concurrently; the result does not depend on it.
        scene_cache: how many level scenes to keep alive (at least 2: the one traced and
            the next, built meanwhile).
        progress: `make_plan`'s stage callback.
    """

    def __init__(self, volume: volumes.Volume, config: BakeConfig, *,
                 lattice: Lattice | None = None, workers: int | None = None,
                 scene_cache: int = 1, progress=None, ahead: int = AHEAD_LEVELS) -> None:
        self.volume, self.config = volume, config
        self.settings = path_settings(volume, config)
        self.geometry = LatticeGeometry.for_volume(volume, config.scale)
        self.lattice = lattice or _new_lattice(volume, config, self.geometry,
                                               self.settings.channels)
        self.lighting = make_lighting(config)
        self.stats = BakeStats()
        self._helper = ThreadPoolExecutor(max_workers=1)  # next level's layout and scene
        self._scenes: OrderedDict[int, object] = OrderedDict()
        self._scene_cache = max(2, scene_cache)
        self._scene_lock = threading.Lock()
        self._pending: dict[int, Future] = {}  # scenes being built ahead
        warm = self._helper.submit(kernels.warm_up)  # loads compiled code beside the plan
        kept = _kept_levels(lattice)
        self._ahead = ahead
        self._first_guess = _first_level(volume, config, kept) if ahead > 0 else None
        if self._first_guess is not None:  # the plan's first level, built beside the plan
            self._pending[0] = self._helper.submit(_level_scene, volume, self._first_guess,
                                                   config)
        self.plan = make_plan(volume, self.geometry, config, kept, progress,
                              on_levels=self._build_first_scenes)
        self.lattice.active = self.plan.active
        warm.result()
        self.texels_done = int(np.count_nonzero(self.samples_done()))
        self.previous = dict(self.lattice.meta.get("stats", {}))
        self._acc = PassSums(len(self.plan.ids), self.settings.channels)
        self._tracing = Tracing(
            self.plan.ids, self.lighting, self.settings, np.uint32(rng.seed_key(config.seed)),
            _luminance_weights(self.settings.channels, self.settings.sh_order is None,
                               self.settings.block if self.settings.sh_split else 0),
            self._acc, whole_paths(self.lighting, self.settings))
        self.workers = max(1, workers or os.cpu_count() or 1)
        self._pool = ThreadPoolExecutor(max_workers=self.workers)
        _finish_meta(self.lattice, self.plan, self.stats, self.previous)

    def samples_done(self, positions: np.ndarray | None = None) -> np.ndarray:
        """(N,) paths already averaged into the texels at plan `positions` (all if None)."""
        ids = self.plan.ids if positions is None else self.plan.ids[positions]
        return self.lattice.samples.reshape(-1)[ids].astype(np.int64)

    def relight(self, config: BakeConfig, lattice: Lattice) -> None:
        """Trace under `config`'s lights into `lattice` from the next `run` on (issue 14: a
        light turned in the viewer, `baking.lazy.Relight`). The plan and the cached level
        scenes stay: they do not depend on the light.

        Raises:
            ValueError: `config` differs from the bake's in more than its env and lights.
        """
        from dataclasses import replace

        if replace(config, env=self.config.env, lights=self.config.lights) != self.config:
            raise ValueError("Baker.relight: only the env and the lights may change")
        self.config, self.lattice = config, lattice
        self.lighting = make_lighting(config)
        self._tracing = replace(
            self._tracing, lighting=self.lighting,
            whole=whole_paths(self.lighting, self.settings))
        self.texels_done = int(np.count_nonzero(self.samples_done()))

    def run(self, positions: np.ndarray | None = None, target: int | np.ndarray | None = None,
            *, bar=None, after_level=None) -> None:
        """Bring the texels at plan `positions` (all if None) up to `target` paths each
        (default `config.samples`).

        Texels are committed to the lattice as soon as their upper level is done, and
        `after_level(committed_positions)` is called then (to upload them, or to save a
        checkpoint). On KeyboardInterrupt committed texels stay and the cut pass of the
        others is dropped whole.
        """
        plan = self.plan
        pending = self.pending(positions, target)
        if pending is None:
            return
        busy, done, remaining, first, last, by_lower = pending
        jobs: list = []
        try:
            # Pipelined: a helper thread lays out the paths and start points of the next
            # level and builds its scene while the workers trace this one (the chunks are
            # compiled calls without the GIL; marching cubes holds it, the BVH build does
            # not). The main thread only waits for what the pipeline did not hide.
            work = self._waited(self._prepare_level, first, by_lower[0], busy[:0], done,
                                remaining)
            for level in range(first, last + 1):
                upcoming = None
                if level < last:
                    upcoming = self._helper.submit(self._prepare_level, level + 1,
                                                   by_lower[level + 1 - first],
                                                   by_lower[level - first], done, remaining)
                jobs = self._submit_level(work)
                self._collect(jobs, level, bar)
                jobs = []
                if upcoming is not None:
                    work = self._waited(upcoming.result)
                # a texel's pass is complete once its upper level is done
                complete = by_lower[level - first - 1] if level > first else busy[:0]
                complete = complete[self._acc.n[complete] > 0]
                if len(complete):
                    self.texels_done += _commit(self.lattice, plan, self._acc, complete)
                    if bar is not None:  # the texels just done (the last level's too)
                        self._show(bar, level, refresh=True)
                    if after_level is not None:
                        after_level(complete)
        except BaseException:
            _cancel(jobs)
            self._acc.clear(busy)
            raise
        finally:
            _finish_meta(self.lattice, plan, self.stats, self.previous)

    def pending(self, positions: np.ndarray | None, target: int | np.ndarray | None):
        """What `run(positions, target)` has to do, or None when nothing.

        Returns:
            busy (B,) plan positions that need paths; done, remaining (T,) paths done and
            still to trace per plan position (0 outside `positions`); the first and last
            level (`last` = the highest lower level + 1) and, for each level from `first`
            to `last`, the busy positions whose lower level it is.
        """
        plan = self.plan
        positions = np.arange(len(plan.ids)) if positions is None else np.unique(positions)
        target = self.config.samples if target is None else target
        done = np.zeros(len(plan.ids), np.int64)
        remaining = np.zeros(len(plan.ids), np.int64)
        done[positions] = self.samples_done(positions)
        remaining[positions] = np.maximum(np.asarray(target) - done[positions], 0)
        busy = positions[remaining[positions] > 0]
        if len(busy) == 0:
            return None
        first, last = int(plan.lower[busy].min()), int(plan.lower[busy].max()) + 1
        return busy, done, remaining, first, last, _group_by(plan.lower[busy], busy, first,
                                                             last)

    def close(self) -> None:
        """Stop the worker threads and drop the cached scenes."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._helper.shutdown(wait=True, cancel_futures=True)
        self._scenes.clear()
        self._pending.clear()

    def _build_first_scenes(self, levels: np.ndarray) -> None:
        """Build the scenes of the lowest `ahead` levels (where a whole bake starts) on the
        helper thread while the plan goes on (`make_plan`'s `on_levels`); level 0's is the
        one started before the plan (`_first_level`) when the guess was right. None with
        `ahead` 0 (a cluster bake's workers build the scenes)."""
        for level in range(min(self._ahead, len(levels))):
            if level > 0 or self._first_guess != float(levels[0]):
                self._pending[level] = self._helper.submit(_level_scene, self.volume,
                                                           float(levels[level]), self.config)

    def _scene(self, level: int):
        """The Embree scene of `level`, from the cache, from the scenes built ahead, or
        built now (least recently used scenes out: the cache holds at least the level
        being traced and the next)."""
        with self._scene_lock:
            if level in self._scenes:
                self._scenes.move_to_end(level)
                return self._scenes[level]
            ahead = self._pending.pop(level, None)
        scene = ahead.result() if ahead is not None else _level_scene(
            self.volume, float(self.plan.levels[level]), self.config)
        with self._scene_lock:
            self.stats.mesh_seconds += scene.mesh_seconds
            self.stats.embree_seconds += scene.build_seconds
            self.stats.scenes += 1
            while len(self._scenes) >= self._scene_cache:
                self._scenes.popitem(last=False)
            self._scenes[level] = scene
        return scene

    def _waited(self, function, *args):
        """`function(*args)`, its wall time counted as waiting for level scenes."""
        began = time.perf_counter()
        try:
            return function(*args)
        finally:
            self.stats.scene_seconds += time.perf_counter() - began

    def _prepare_level(self, level: int, here: np.ndarray, below: np.ndarray,
                       done: np.ndarray, remaining: np.ndarray) -> _LevelWork:
        """Lay out every pending path of isovalue level `level`, sorted by texel, with
        the start points of its texels — the lower-level samples of the texels whose
        lower level it is (`here`), and the upper-level samples of those whose lower
        level is the one below (`below`) — and get the level's scene if it has paths."""
        plan = self.plan
        pos, samples, start = lay_out_level(
            self.volume, self.geometry, self.config, float(plan.levels[level]), plan.ids,
            plan.phase, plan.weight, here, below, done, remaining, plan.landing)
        scene = self._scene(level) if len(pos) else None
        return _LevelWork(level, pos, samples, start, scene)

    def _submit_level(self, work: _LevelWork) -> list:
        """Queue the level's chunks of paths on its scene.

        Workers add their per-texel sums straight into the pass accumulator: the chunks
        of one level hold disjoint texels, and a texel is committed only after its last
        level has been collected.
        """
        if len(work.pos) == 0:
            return []
        return [self._pool.submit(trace_chunk, work.scene, self._tracing, work.pos[lo:hi],
                                  work.samples[lo:hi], work.start)
                for lo, hi in _chunk_bounds(work.pos, self.workers)]

    def _collect(self, jobs: list, level: int, bar) -> None:
        """Wait for the chunks of `level`; count their paths and rays.

        The progress bar moves every `REPORT_S` seconds and at the end: waking up for
        every finished chunk would take the GIL from the workers a hundred times a level.
        """
        pending = set(jobs)
        while pending:
            finished, pending = wait(pending, timeout=REPORT_S)
            for job in finished:
                paths, rays, seconds = job.result()
                self.stats.add_rays(rays, seconds)
                self.stats.paths += paths
                if bar is not None:
                    bar.update(paths)
            if bar is not None:
                self._show(bar, level)

    def _show(self, bar, level: int, refresh: bool = False) -> None:
        """The progress bar's texels done, level and ray rate."""
        elapsed = time.perf_counter() - self.stats.started
        bar.set_postfix_str(
            f"texels {self.texels_done:,}/{len(self.plan.ids):,} "
            f"level {level + 1}/{len(self.plan.levels)} "
            f"{self.stats.rays / max(elapsed, 1e-9) / 1e6:.2f} Mrays/s", refresh=refresh)


def _cancel(jobs: list) -> None:
    """Cancel queued chunks and wait for running ones (they add to the accumulator)."""
    for job in jobs:
        job.cancel()
    for job in jobs:
        if not job.cancelled():
            job.exception()


def _group_by(keys: np.ndarray, values: np.ndarray, first: int, last: int) -> list:
    """[values with key k for k in first..last]: one stable sort instead of a scan per k."""
    order = np.argsort(keys, kind="stable")
    bounds = np.searchsorted(keys[order], np.arange(first, last + 2))
    return [values[order[lo:hi]] for lo, hi in itertools.pairwise(bounds)]


def bake(volume: volumes.Volume, config: BakeConfig, *, out: str | os.PathLike | None = None,
         workers: int | None = None, progress: bool = False,
         checkpoint_seconds: float = 60.0, scheduler: str | None = None) -> Lattice:
    """Bake (or resume) the illumination lattice of `volume` for `config`.

    Args:
        out: lattice file; if it exists with the same volume and settings, the bake
            resumes and brings every active texel up to `config.samples` paths.
        workers: threads tracing concurrently (default: CPU count). The result does not
            depend on it.
        progress: show a progress bar (texels, rays per second) on stderr.
        checkpoint_seconds: save finished texels to `out` at least this often.
        scheduler: trace on a Dask cluster instead of local threads (``tcp://HOST:PORT``
            or ``local:N``; `baking.cluster`): the same lattice to the bit.

    Returns:
        The lattice (also written to `out`; on Ctrl-C the finished texels are saved
        before KeyboardInterrupt propagates).
    """
    out = Path(out) if out is not None else None
    existing = _load_existing(volume, config, out)
    if scheduler is not None:
        from isolume.baking.cluster import ClusterBaker

        baker = ClusterBaker(volume, config, scheduler, lattice=existing)
    else:
        baker = Baker(volume, config, lattice=existing, workers=workers,
                      progress=_plan_progress if progress else None)
    pending = np.maximum(config.samples - baker.samples_done(), 0)
    bar = _progress(int(pending.sum()), progress)
    last_save = [time.perf_counter()]

    def checkpoint(_committed: np.ndarray) -> None:
        if out is not None and time.perf_counter() - last_save[0] > checkpoint_seconds:
            baker.lattice.save(out)
            last_save[0] = time.perf_counter()

    try:
        baker.run(bar=bar, after_level=checkpoint)
        if config.target_error is not None:
            _refine_to_target(baker, bar, checkpoint)
    except KeyboardInterrupt:
        if out is not None:
            baker.lattice.save(out)
        raise
    finally:
        baker.close()
        bar.close()
    if out is not None:
        baker.lattice.save(out)
    return baker.lattice


def _refine_to_target(baker: Baker, bar, checkpoint, passes: int = 4) -> None:
    """Give more samples to texels whose relative standard error exceeds the target.

    The error falls as 1/sqrt(n), so a texel with error e after n paths needs about
    n (e / target)² in all; each pass asks for 1.2 times that (at most 8 n, at most
    `max_samples`), so a few passes — each rebuilding the level scenes — suffice.
    """
    config = baker.config
    for _ in range(passes):
        error = baker.lattice.relative_error().reshape(-1)[baker.plan.ids]
        done = baker.samples_done()
        todo = np.flatnonzero((error > config.target_error) & (done < config.max_samples))
        if len(todo) == 0:
            return
        need = 1.2 * done[todo] * (error[todo] / config.target_error) ** 2
        target = np.minimum(np.clip(np.ceil(need), done[todo] + 1, 8 * done[todo]),
                            config.max_samples).astype(np.int64)
        if bar is not None:
            bar.total += int((target - done[todo]).sum())
        baker.run(todo, target, bar=bar, after_level=checkpoint)


@dataclass(frozen=True)
class _LevelWork:
    """The pending paths of one level: texel positions (P,) sorted, sample indices (P,),
    the start points of their texels, and the level's `trace.Scene` (None when P = 0)."""

    level: int
    pos: np.ndarray
    samples: np.ndarray
    start: PathStarts
    scene: object


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
                  here: np.ndarray, below: np.ndarray, done: np.ndarray,
                  remaining: np.ndarray, landing: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, PathStarts]:
    """The pending paths of the level surface ρ = `iso` and their texels' start points
    (`Baker._prepare_level`; a cluster task lays out its own texels with it). Each
    texel's paths and start point depend on that texel alone.

    Args:
        ids, phase, weight: (T,) the plan's lattice ids, level phases and upper weights,
            of all its texels or of any subset (positions then index the subset).
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
                                    on_level)
    return pos, samples, PathStarts(texels, origins.astype(np.float32),
                                    normals.astype(np.float32))


@dataclass(frozen=True)
class Tracing:
    """What every chunk of a bake traces with, made once per bake.

    Attributes:
        ids: (A,) flat lattice ids of the plan's texels.
        seed_key: ``pcg_hash(seed)``, the start of every path key.
        weights: (C,) `_luminance_weights` of the second moments.
        acc: the pass sums the chunks add to.
        whole: parameters of `integrator.trace_whole_paths` where it covers the bake's
            lighting, else None (`integrator.whole_paths`).
    """

    ids: np.ndarray
    lighting: Lighting
    settings: PathSettings
    seed_key: np.uint32
    weights: np.ndarray
    acc: PassSums
    whole: WholePaths | None


def trace_chunk(scene, tracing: Tracing, pos, samples,
                 start: PathStarts) -> tuple[int, int, float]:
    """Worker: trace paths (sorted texel positions `pos`, sample indices) from their start
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


def _level_scene(volume: volumes.Volume, iso: float, config: BakeConfig):
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
        "iso_range": [float(v) for v in plan.iso_range],
        "move_limit_voxels": plan.move_limit,
        "noise_sigma": plan.noise,
        "move_voxels_p50": float(np.percentile(plan.move_voxels, 50)),
        "move_voxels_p90": float(np.percentile(plan.move_voxels, 90)),
        "move_voxels_max": float(plan.move_voxels.max()),
    }
