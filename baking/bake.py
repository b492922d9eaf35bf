"""The baker: fills a lattice by path tracing, level by level.

Order of work: for each isovalue level (one marching-cubes mesh and one Embree scene alive
at a time), the texels that bracket it trace the paths assigned to it, in chunks of whole
texels, on worker threads or on a Dask cluster (`baking.backend`). A texel's pass is
complete once its upper level is done; complete texels are committed to the lattice
(running means and sample counts), which is saved atomically at checkpoints, at the end,
and on Ctrl-C — finished work is never lost, and running the same bake again resumes
where it stopped.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from isolume import volumes
from isolume.baking import kernels, rng
from isolume.baking.adaptive import (
    ROUND_KEY,
    RoundState,
    group_brightness,
    ladder,
    path_spread,
    still_going,
)
from isolume.baking.backend import (
    BakeJob,
    BakeStats,
    PassReport,
    PassWork,
    ThreadBackend,
    TracingBackend,
    scene_budget,
)
from isolume.baking.config import BakeConfig
from isolume.baking.density import bake_texels, clear_filled, refilled, texel_luminance
from isolume.baking.environment import ConstantEnvironment
from isolume.baking.errors import BakeError, BakeInterrupted
from isolume.baking.integrator import PathSettings, TracingLights, whole_paths
from isolume.baking.lattice import (
    LUMINANCE,
    TRAPPED_PATHS,
    Lattice,
    LatticeGeometry,
    open_lattice,
    other_texels,
    sky_everywhere,
    volume_identity,
)
from isolume.baking.lattice_file import LatticeFile, quick_saves
from isolume.baking.passes import (
    PassSums,
    Tracing,
    commit_facing,
    commit_sums,
    rows_at,
    stratifies,
)
from isolume.baking.plan import Plan, as_planned, index_type, make_plan
from isolume.baking.plan_lattice import PlanLattice
from isolume.baking.plan_records import HeldRecords, LevelGroups, PlanRecords, spill
from isolume.baking.saves import (
    CHECKPOINT_S,
    Checkpoints,
    save_interrupted,
    save_through,
    through_one_interrupt,
)
from isolume.volumes import cores
from isolume.volumes.errors import interrupted_by


def tracing_lights(config: BakeConfig) -> TracingLights:
    """What the integrator needs of `config`'s lighting: the environment, whether to sample
    it, the lights and the compiled sky's parameters; the lights' and the sun's direct
    light is left to the renderer when `config.direct_light` is "pixels"."""
    lighting = config.lighting
    env = lighting.environment
    sample_env = env is not None and not isinstance(env, ConstantEnvironment)
    sky = kernels.sky_params(env) if lighting.sky is not None else None
    return TracingLights(env, sample_env, lighting.lights, sky,
                         pixel_direct=config.direct_light == "pixels")


def path_settings(volume: volumes.Volume, config: BakeConfig) -> PathSettings:
    """Integrator parameters for `config` on `volume`."""
    h = float(min(volume.spacing))
    return PathSettings(
        bounces=config.bounces, albedo=config.albedo, hit_offset=2e-3 * h,
        sh_order=config.sh_order if config.mode == "sh" else None,
        rgb_transfer=config.mode == "sh" and not config.gray,
        # an SH bake with the sun per pixel keeps direct and indirect
        # transfer apart (`baking.integrator` module docs)
        sh_split=config.mode == "sh" and config.direct_light == "pixels",
    )


def _luminance_weights(channels: int, irradiance: bool, second_block: int = 0) -> np.ndarray:
    """(C,) weights of the brightness whose variance the error estimates use: luminance
    of RGB irradiance, the DC coefficient of SH transfer (of both blocks of a split
    transfer, the second starting at `second_block`)."""
    weights = np.zeros(channels)
    if irradiance:
        weights[:3] = LUMINANCE
    else:
        weights[0] = weights[second_block] = 1.0
    return weights


def lattice_meta(volume: volumes.Volume, config: BakeConfig, channels: int,
                 hashed: bool = True) -> dict[str, Any]:
    """The metadata that identifies the volume and the bake of a lattice of `channels`
    values per texel (`hashed`: with the volume's hash, `volume_identity`)."""
    return {"kind": config.mode, "sh_order": config.sh_order if config.mode == "sh" else None,
            "scale": config.scale, "volume": volume_identity(volume, hashed),
            "channels": channels}


def _new_lattice(volume: volumes.Volume, config: BakeConfig, geometry: LatticeGeometry,
                 channels: int) -> Lattice:
    """An empty lattice with the metadata that identifies the volume and the bake."""
    lattice = Lattice.empty(geometry, channels, lattice_meta(volume, config, channels))
    lattice.config = config
    return lattice


def _kept_levels(lattice: Lattice | LatticeFile | None) -> np.ndarray | None:
    """(K,) the levels a lattice (or a lattice file, opened) was started with (a resumed
    bake keeps them: its samples were traced on them), or None."""
    if lattice is None or "plan" not in lattice.meta:
        return None
    return np.asarray(lattice.meta["plan"]["levels"], np.float64)


def _resumable(volume: volumes.Volume, config: BakeConfig, out: Path | None
               ) -> LatticeFile | None:
    """The lattice file `out` opened when it can be resumed with `config`, None when there
    is none (its texels are read once the plan says which, `PlanLattice.fill_from`).

    Raises:
        BakeError: `out` holds a lattice of another volume or other settings.
    """
    if out is None or not out.exists():
        return None
    file, geometry, previous = open_lattice(out, volume)
    if previous is None:
        raise BakeError(f"{out}: records no bake settings; to bake, write to a new --out "
                        "file")
    if not previous.same_result_as(config):
        raise BakeError(f"{out}: holds a bake with other settings ("
                        f"{'; '.join(previous.differences(config))}); to resume, repeat "
                        "them, or write to a new --out file")
    problem = other_texels(geometry, volume, config.scale, out)
    if problem:
        raise BakeError(problem)
    return file


BAR_REFRESH_S = 0.1
"""Seconds between redraws of a plan stage's progress bar."""


class _PlanBars:
    """The plan's stages on stderr as progress bars, one a stage, while `enabled`
    (`make_plan`'s ``progress(stage[, fraction])``: a large volume's plan takes minutes).
    A context: a stage's bar is full once the next stage starts or the plan returns, and
    stays where it got to when the plan fails."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.stage: str | None = None
        self.bar = None
        self.shown = 0.0  # when the bar was last drawn

    def __enter__(self) -> _PlanBars:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        self._end(finished=kind is None)

    def __call__(self, stage: str, fraction: float | None = None) -> None:
        from tqdm.auto import tqdm

        if stage != self.stage:
            self._end(finished=True)
            self.stage = stage
            self.bar = tqdm(total=100, desc=f"planning: {stage}", dynamic_ncols=True,
                            disable=not self.enabled,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")
        if fraction is not None:
            self.bar.n = min(100.0, 100.0 * fraction)
            now = time.perf_counter()
            if now - self.shown >= BAR_REFRESH_S or self.bar.n >= 100.0:
                self.bar.refresh()  # not at every block: a bar drawn costs 0.2 ms
                self.shown = now

    def _end(self, finished: bool) -> None:
        """End the current stage's bar, full when the stage `finished`."""
        if self.bar is not None:
            if finished:
                self.bar.n = 100
            self.bar.close()
            self.bar = None


def _progress(total: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, unit="path", unit_scale=True, disable=not enabled,
                dynamic_ncols=True, smoothing=0.1, desc="baking")


class Baker:
    """A lattice being baked: the plan, the lighting, the pass sums and the lattice; the
    paths are traced by a `TracingBackend` (local threads unless `backend` says otherwise).

    `run` brings any subset of the active texels up to a sample count, a batch of texels at
    a time on their two levels, so the same machinery serves a full bake (all texels to
    `config.samples`) and a lazy, progressive one (the texels around the displayed
    isosurface first, a few samples at a time).

    Args:
        lattice: a lattice dense over the box to extend (the viewer's shared one, a
            resumed bake); None starts empty.
        packed: hold the lattice over the plan's texels only (a `PlanLattice`, whose
            memory follows the active texels); `lattice` is then not used, and `resume`
            (a lattice file opened, `open_lattice`: its texels not read) gives the samples
            to extend. Such a Baker is never replanned, its plan keeps no `rho` and
            `target` (`Plan.traced_only`), and its texel records are kept in a temporary
            file in `records_dir` (`plan_records.spill`; the system's temporary
            directory if None), read back a batch of texels at a time.
        workers, scene_cache, scene_memory: the `ThreadBackend`'s threads, level scenes
            kept alive, and bytes of level scenes kept beyond those, when no `backend` is
            given. The result does not depend on them.
        progress: `make_plan`'s stage callback.
        backend: who traces the paths (e.g. `cluster.ClusterBackend`); the Baker closes
            it in `close`, or when the Baker cannot be made.

    Attributes:
        facings_made: every texel's facing was made for this plan (`baking.density`
            makes them all before tracing): commits keep them rather than make them
            again for texels without samples.
    """

    def __init__(self, volume: volumes.Volume, config: BakeConfig, *,
                 lattice: Lattice | None = None, workers: int | None = None,
                 scene_cache: int = 1, scene_memory: float = 0.0,
                 progress: Callable[..., None] | None = None,
                 backend: TracingBackend | None = None, packed: bool = False,
                 resume: LatticeFile | None = None,
                 records_dir: str | os.PathLike[str] | None = None) -> None:
        self.backend: TracingBackend = (
            backend if backend is not None
            else ThreadBackend(workers, scene_cache, scene_memory=scene_memory))
        self.records: PlanRecords | None = None
        try:
            self.volume: volumes.Volume = volume
            self.config: BakeConfig = config
            self.settings: PathSettings = path_settings(volume, config)
            self.geometry: LatticeGeometry = LatticeGeometry.for_volume(volume, config.scale)
            self.lighting: TracingLights = tracing_lights(config)
            self.stats: BakeStats = BakeStats()
            source = resume if packed else lattice
            kept = _kept_levels(source)
            planned = as_planned(config, source.meta if source is not None else {})
            self.backend.begin(volume, planned, kept, self.stats)  # beside the plan
            self.plan: Plan = make_plan(volume, self.geometry, planned, kept, progress,
                                        on_levels=self.backend.levels_known,
                                        scenes=self.backend.plan_scene, traced_only=packed)
            self.groups: LevelGroups = LevelGroups(self.plan.lower)  # every texel's, by lower level
            self.lattice: Lattice | PlanLattice
            self.rows: np.ndarray | None
            if packed:  # never replanned: see `relight`
                self.plan, self.records = spill(self.plan, records_dir, self.groups)
                self.lattice, self.rows = self._plan_lattice(resume), None
            else:
                self.records = HeldRecords(self.plan)
                self.lattice = lattice or _new_lattice(volume, config, self.geometry,
                                                       self.settings.channels)
                self.lattice.active, self.rows = self.plan.active, self.plan.ids
            self.texels_done: int = int(np.count_nonzero(self.samples_done()))
            self.previous: dict[str, Any] = dict(self.lattice.meta.get("stats", {}))
            self.facings_made: bool = False
            self.job: BakeJob = BakeJob(volume, planned, self.geometry, self.plan,
                                        self.records, self._tracing(), self.stats)
            self.backend.start(self.job)
        except BaseException as error:
            self.close(wait=not interrupted_by(error))
            raise
        self._finish_meta()

    def _plan_lattice(self, resume: LatticeFile | None) -> PlanLattice:
        """The lattice over the plan's texels, with `resume`'s samples of them."""
        meta = (resume.meta if resume is not None
                else lattice_meta(self.volume, self.config, self.settings.channels))
        lattice = PlanLattice(self.geometry, self.plan.ids, self.settings.channels, meta,
                              self.config)
        if resume is not None:
            lattice.fill_from(resume)
        return lattice

    def _tracing(self) -> Tracing:
        """What every chunk traces with: the plan's texels, the lighting, the path keys of
        the seed, the pass sums."""
        settings = self.settings
        weights = _luminance_weights(settings.channels, settings.sh_order is None,
                                     settings.block if settings.sh_split else 0)
        seed_key = np.uint32(rng.seed_key(self.config.seed))
        return Tracing(self.plan.ids, self.lighting, settings, seed_key, weights,
                       whole_paths(self.lighting, settings), stratifies(self.config))

    def samples_done(self, positions: np.ndarray | None = None) -> np.ndarray:
        """(N,) paths already averaged into the texels at plan `positions` (all if None)."""
        samples = self.lattice.samples.reshape(-1)
        if positions is None:
            return (samples if self.rows is None else samples[self.rows]).astype(np.int64)
        return samples[rows_at(self.rows, positions)].astype(np.int64)

    def rows_of(self, positions: np.ndarray) -> np.ndarray:
        """(N,) rows of the texels at plan `positions` in the lattice's flattened arrays."""
        return rows_at(self.rows, positions)

    def relight(self, config: BakeConfig, lattice: Lattice) -> None:
        """Trace under `config`'s lights into `lattice` from the next `run` on (a light
        turned in the viewer, `baking.lazy.Relight`). The plan and the backend's level
        scenes stay: they do not depend on the light.

        Raises:
            ValueError: `config` differs from the bake's in more than its env and lights,
                or the Baker holds its lattice over the plan (``packed``).
        """
        if replace(config, env=self.config.env, lights=self.config.lights) != self.config:
            raise ValueError("Baker.relight: only the env and the lights may change")
        if self.rows is None:
            raise ValueError("Baker.relight: a packed Baker has no lattice dense over the box")
        self.config, self.lattice = config, lattice
        self.lighting = tracing_lights(config)
        self.job = replace(self.job, config=config, tracing=self._tracing())
        self.backend.start(self.job)
        self.texels_done = int(np.count_nonzero(self.samples_done()))

    def run(self, positions: np.ndarray | None = None, target: int | np.ndarray | None = None,
            *, bar: Any = None,
            after_commit: Callable[[np.ndarray], object] | None = None) -> None:
        """Bring the texels at plan `positions` (all if None) up to `target` paths each
        (default `config.samples`).

        Texels are committed to the lattice as soon as their upper level is done (a batch
        of them at a time, `backend.TEXELS_PER_BATCH` on local threads), and
        `after_commit(committed_positions)` is called then (to upload them, or to save a
        checkpoint). On KeyboardInterrupt committed texels stay and the cut pass of the
        others is dropped whole.
        """
        work = self.pending(positions, target)
        if work is None:
            return

        def commit(positions: np.ndarray, sums: PassSums) -> int:
            traced = np.flatnonzero(sums.n > 0)
            complete = positions[traced]
            if len(complete):
                commit_facing(self.lattice, self.volume, self.config, self.plan,
                              self.records, complete, self.rows,
                              unsampled=not self.facings_made)
            self.texels_done += commit_sums(self.lattice, rows_at(self.rows, positions),
                                            sums, traced)
            if len(complete) and after_commit is not None:
                after_commit(complete)
            return len(complete)

        try:
            self.backend.trace_pass(work, PassReport(commit, bar, self._status))
        finally:
            self._finish_meta()
            self.backend.record(self.lattice.meta)

    def pending(self, positions: np.ndarray | None,
                target: int | np.ndarray | None) -> PassWork | None:
        """What `run(positions, target)` has to do, or None when nothing."""
        plan = self.plan
        if len(plan.ids) == 0:
            return None
        target = self.config.samples if target is None else target
        if positions is None and np.ndim(target) == 0:
            held = self.lattice.samples.reshape(-1)
            held = held if self.rows is None else held[self.rows]
            if held.min() == held.max():  # every texel alike: no per-texel counts
                return self._alike(int(held[0]), int(target))
            del held
        index = index_type(len(plan.ids))
        positions = (np.arange(len(plan.ids), dtype=index) if positions is None
                     else sorted_unique(positions).astype(index, copy=False))
        had = self.samples_done(positions)
        wanted = np.maximum(np.asarray(target) - had, 0)
        count = _count_type(int((had + wanted).max(initial=0)))
        needs = wanted > 0
        busy = positions[needs]
        if len(busy) == 0:
            return None
        lower = plan.lower[busy]
        return PassWork(had[needs].astype(count), wanted[needs].astype(count),
                        int(lower.min()), int(lower.max()) + 1, LevelGroups(plan.lower, busy))

    def _alike(self, done: int, target: int) -> PassWork | None:
        """The pass that brings every texel of the plan from `done` paths to `target`."""
        wanted = max(target - done, 0)
        if wanted == 0:
            return None
        count = _count_type(done + wanted)
        lower = self.plan.lower
        return PassWork(np.array(done, count), np.array(wanted, count), int(lower.min()),
                        int(lower.max()) + 1, self.groups)

    def close(self, wait: bool = True) -> None:
        """Close the backend (its threads, its cluster connection, its scenes; without
        `wait`, as a Ctrl-C does, work still running on its threads ends there) and let go
        of the plan's records."""
        self.backend.close(wait)
        if self.records is not None:
            self.records.close()

    def _finish_meta(self) -> None:
        """Record what the bake did in the lattice metadata (the module's `_finish_meta`)."""
        _finish_meta(self.lattice, self.plan, self.records.high_texels, self.stats,
                     self.previous)

    def _status(self, level: int, note: str = "") -> str:
        """The progress bar's texels done, level, a backend's `note` and the ray rate."""
        elapsed = time.perf_counter() - self.stats.started
        return (f"texels {self.texels_done:,}/{len(self.plan.ids):,} "
                f"level {level + 1}/{len(self.plan.levels)} {note}"
                f"{self.stats.rays / max(elapsed, 1e-9) / 1e6:.2f} Mrays/s")


def sorted_unique(positions: np.ndarray) -> np.ndarray:
    """`numpy.unique` of (N,) `positions`, without its sort where they already rise."""
    positions = np.asarray(positions)
    if len(positions) < 2 or bool(np.all(positions[1:] > positions[:-1])):
        return positions
    return np.unique(positions)


def _count_type(most: int) -> type:
    """The type of a pass's per-texel sample counts (`PassWork.done`, `remaining`) when
    none exceeds `most`: uint16 (2 bytes a texel; samples stop at `BakeConfig.max_samples`,
    4096 by default), else int32."""
    return np.uint16 if most <= np.iinfo(np.uint16).max else np.int32


@dataclass(frozen=True)
class BakeOutlook:
    """What a bake is about to trace, known once its plan is made.

    Attributes:
        texels: active texels; levels: isovalue levels; paths: paths still to trace
            (about, with a noise target or a texel error: `_outlook_samples` a texel);
        threads: local tracing threads (0 on a cluster); resumed: texels that have
            paths already (from the --out file a bake resumes; 0 for a new bake).
    """

    texels: int
    levels: int
    paths: int
    threads: int
    resumed: int = 0

    def minutes(self) -> float | None:
        """Rough wall time in minutes on local threads at `PATHS_PER_THREAD_SECOND` (None
        on a cluster)."""
        if self.threads == 0:
            return None
        return self.paths / (PATHS_PER_THREAD_SECOND * self.threads) / 60


PATHS_PER_THREAD_SECOND = 5e5
"""Paths per second and thread of a default bake (2 bounces under the default sky), in
round figures: the bonsai at 128³ and iso 22 traced 51.5 M paths in 42.5 s on the two
threads of the machine the docs' figures come from (0.6 M per thread)."""


def bake(volume: volumes.Volume, config: BakeConfig, *, out: str | os.PathLike[str] | None = None,
         workers: int | None = None, progress: bool = False,
         checkpoint_seconds: float = CHECKPOINT_S, scheduler: str | None = None,
         outlook: Callable[[BakeOutlook], None] | None = None,
         dense: bool = True, keep_interrupted: bool = False,
         scene_memory: float | None = None) -> Lattice | PlanLattice:
    """Bake (or resume) the illumination lattice of `volume` for `config`.

    Args:
        out: lattice file; if it exists with the same volume and settings, the bake
            resumes and brings every active texel up to `config.samples` paths.
        workers: threads tracing concurrently (default: CPU count). The result does not
            depend on it.
        progress: show a progress bar (texels, rays per second) on stderr.
        checkpoint_seconds: save finished texels to `out` once this long has passed
            since the last save, or later where saving would take more than
            `baking.saves.SAVE_SHARE` of the time (`Checkpoints`).
        scheduler: trace on a Dask cluster instead of local threads (``tcp://HOST:PORT``
            or ``local:N``; `baking.cluster`): the same lattice to the bit.
        outlook: told what the bake is about to trace (`BakeOutlook`) once the plan is
            made, before any path.
        dense: return the lattice dense over the box; False: as the bake held it, over
            the plan's texels (`PlanLattice`: what a caller that only writes `out` needs;
            dense arrays take 23 bytes a texel of the box in irradiance, 3.1 GB at 512³).
        keep_interrupted: on Ctrl-C (a notebook's interrupt), return the lattice of the
            finished texels (``meta["interrupted"]`` True) instead of raising.
        scene_memory: bytes of level scenes kept for good, so that each is built once for
            the plan's side probes and every pass (`ThreadBackend`: beside its cache of
            one scene, two for a target; a thread bake's only); None:
            `backend.scene_budget` for a bake in several passes (to a texel error or a
            target), 0 for one of `samples` paths a texel (one pass: the scenes kept would
            spare only the side probes' builds).

    Returns:
        The lattice (also written to `out`; on Ctrl-C the finished texels are saved,
        quickly (`lattice_file.quick_saves`), before `errors.BakeInterrupted` (a
        KeyboardInterrupt that counts them) propagates, or before they are returned (a
        second Ctrl-C stops that save: `errors.SaveAbandoned`, `out` as it was); a
        Ctrl-C while the finished bake is saved lets that save end first, a second
        abandons it, leaving `out` as it was: `baking.saves.through_one_interrupt`).
    """
    out = Path(out) if out is not None else None
    resume = _resumable(volume, config, out)
    adaptive = config.target_error is not None
    if scene_memory is None:
        several = adaptive or config.texel_error is not None
        scene_memory = scene_budget() if several else 0.0
    backend = None
    if scheduler is not None:
        from isolume.baking.cluster import ClusterBackend

        backend = ClusterBackend(scheduler)
    with _PlanBars(progress) as bars:
        baker = Baker(volume, config, workers=workers, backend=backend, progress=bars,
                      packed=True, resume=resume, scene_cache=2 if adaptive else 1,
                      scene_memory=scene_memory,
                      records_dir=out.parent if out is not None else None)
    cleared = clear_filled(baker.lattice, len(baker.plan.ids), config.texel_error is not None)
    done = baker.samples_done()
    done[refilled(baker.lattice, config, cleared, len(baker.plan.ids))] = config.samples
    pending = int(np.maximum(config.samples - done, 0).sum())  # the first round's
    if outlook is not None:
        threads = 0 if scheduler is not None else (workers or cores.threads())
        expected = int(np.maximum(_outlook_samples(config) - done, 0).sum())
        outlook(BakeOutlook(len(baker.plan.ids), len(baker.plan.levels), expected, threads,
                            int(np.count_nonzero(done))))
    del done
    bar = _progress(pending, progress)
    held = baker.lattice
    checkpoint = Checkpoints(held, out, checkpoint_seconds)
    cores.stage("tracing")
    note = (f"isolume: interrupted; the bake is done and its save to {out} is finished "
            "first, what is left of it uncompressed (Ctrl-C again to stop without it)"
            ) if progress else None
    pressed: list[bool] = []
    stopped = False
    with ExitStack() as finishing:
        try:
            if adaptive:
                bake_to_target(baker, bar, checkpoint)
            elif config.texel_error is not None:
                bake_texels(baker, bar, checkpoint)
            else:
                baker.run(bar=bar, after_commit=checkpoint)
            if out is not None:  # traced: from here on a Ctrl-C lets the save end first
                hurry = finishing.enter_context(quick_saves(now=False))
                pressed = finishing.enter_context(through_one_interrupt(note, hurry))
        except (KeyboardInterrupt, SystemError) as exc:
            if not interrupted_by(exc):  # a Ctrl-C out of numba's kernel loading counts
                raise
            stopped = True
            bar.close()  # its last line stays above what follows
            if out is not None:
                save_interrupted(held, out, progress)
                if not keep_interrupted:
                    raise BakeInterrupted(_finished(held)) from None
            if not keep_interrupted:
                if isinstance(exc, KeyboardInterrupt):
                    raise
                raise KeyboardInterrupt from exc
            held.meta["interrupted"] = True
        finally:
            baker.close(wait=not stopped)
            bar.close()
        cores.stage("save")
        if out is not None and not held.meta.get("interrupted"):
            with cores.timed_item("save"):  # deflated in pieces on the pool (`lattice_file`)
                save_through(held, out)
    if pressed and not keep_interrupted:
        raise BakeInterrupted(_finished(held))
    del baker  # its plan goes before the lattice is made dense
    return held.dense() if dense else held


def _finished(lattice: Lattice | PlanLattice) -> int:
    """Texels of `lattice` with paths."""
    return int(np.count_nonzero(lattice.samples))


def _outlook_samples(config: BakeConfig) -> int:
    """Paths a texel a bake's outlook counts: `samples` for a bake to a texel error (its
    filled texels take none, the nodes that fill twice: 0.3–1.15 × `samples` a texel on
    average over the scans of ``../shared/data`` at the default), else the plan's."""
    return config.samples if config.texel_error is not None else config.plan_samples


def bake_to_target(baker: Baker, bar: Any, checkpoint: Any) -> None:
    """Trace `baker`'s texels group by group in rounds until each meets
    ``config.target_error`` or has ``config.max_samples`` paths (`baking.adaptive`),
    going on from the round recorded in its lattice's metadata."""
    config = baker.config
    rungs = ladder(config.samples, config.max_samples)
    state = RoundState.resumed(baker.lattice.meta.get(ROUND_KEY), config.target_error,
                               config.samples, config.max_samples)
    lower = baker.plan.lower
    if state.finished:
        return
    groups = range(state.group, int(lower.max()) + 1) if len(lower) else range(0)
    for group in groups:
        members = baker.groups.of(group)
        if len(members):
            _bake_group(baker, state, group, members, rungs, bar, checkpoint)
        state.group, state.rung, state.brightness, state.going = group + 1, 0, None, None
    state.finished = True
    baker.lattice.meta[ROUND_KEY] = state.record()


def _bake_group(baker: Baker, state: RoundState, group: int, members: np.ndarray,
                rungs: list[int], bar: Any, checkpoint: Any) -> None:
    """The rounds of one level group (plan positions (N,) `members`) from `state`'s."""
    ids = baker.plan.ids[members]
    shape = baker.geometry.shape
    dark_until = TRAPPED_PATHS if sky_everywhere(baker.config) else 0
    weights = baker.job.tracing.weights
    while True:
        state.group = group
        baker.lattice.meta[ROUND_KEY] = state.record()
        going = (np.ones(len(members), bool) if state.going is None else state.going)
        todo = members[going]
        target = rungs[state.rung]
        if bar is not None and state.rung > 0:  # the first round's are in its total
            bar.total += int(np.maximum(target - baker.samples_done(todo), 0).sum())
        baker.run(todo, target, bar=bar, after_commit=checkpoint)
        rows = baker.rows_of(members)
        luminance = texel_luminance(baker.lattice.values.reshape(-1, len(weights))[rows],
                                    weights)
        second = baker.lattice.second.reshape(-1)[rows]
        samples = baker.samples_done(members)
        which = np.flatnonzero(going)
        spread = path_spread(luminance, second, samples, ids, shape, which)
        if state.brightness is None:
            state.brightness = group_brightness(luminance)
            state.spread = float(np.mean(spread)) if len(spread) else 0.0
        if state.rung + 1 >= len(rungs):
            return
        going = np.zeros(len(members), bool)
        going[which] = still_going(spread, samples[which], state.brightness, state.spread,
                                   state.target, rungs[-1], luminance[which] == 0,
                                   dark_until)
        if not going.any():
            return
        state.rung, state.going = state.rung + 1, going


def _finish_meta(lattice: Lattice | PlanLattice, plan: Plan, high_texels: int, stats: BakeStats,
                 previous: dict) -> None:
    """Record what the bake did (adding to the counts of earlier runs on the same file);
    `high_texels`: the plan's texels lit on the high-value side."""
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
    moves = plan.moves.figures()
    lattice.meta["plan"] = {
        "active_texels": len(plan.ids),
        "unreachable_texels": plan.unreachable,
        "high_side_texels": high_texels,
        "total_texels": int(math.prod(lattice.geometry.shape)),
        "levels": [float(v) for v in plan.levels],
        "iso_range": [float(v) for v in plan.iso_range],
        "move_limit_voxels": plan.move_limit,
        "move_voxels_p50": moves[0],
        "move_voxels_p90": moves[1],
        "move_voxels_max": moves[2],
    }
