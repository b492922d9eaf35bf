"""Who traces a bake's paths: one small protocol, local threads by default.

A `bake.Baker` plans the bake, holds the lattice and commits texels; it hands the tracing
of its passes to a `TracingBackend` — `ThreadBackend` (worker threads of this process) or
`cluster.ClusterBackend` (tasks on a Dask cluster). A backend forms the pass sums of some
texels — each texel's paths on its lower level, then on its upper one — and hands them
to the Baker to commit (`PassReport.commit`). The pieces of a pass are `baking.passes`'s,
so the lattice is the same bits whatever the backend, its number of workers and the
texels it commits together.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np

from isolume import volumes
from isolume.baking import kernels
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.passes import (
    LevelPaths,
    LevelStarts,
    PassSums,
    Tracing,
    chunk_bounds,
    lay_out_level,
    level_scene,
    trace_texels,
)
from isolume.baking.plan import Plan, index_type
from isolume.baking.plan_records import LevelGroups, PlanRecords
from isolume.volumes import cores
from isolume.volumes.io.common import available_memory

if TYPE_CHECKING:  # embreex is imported only when a bake runs
    from isolume.baking.trace import Scene

AHEAD_LEVELS = 1
"""Scenes of the highest levels a `ThreadBackend` builds beside the plan: the helper
thread is done with the top level's before the plan's side probes start on it (they go
down the levels, leaving the lowest one's scene, where the tracing starts, in the
cache)."""
SCENE_BYTES_PER_TRIANGLE = 100
"""Memory of one triangle of a level scene, rounded up: its mesh arrays (about 18 bytes,
`volumes.tracing_surface`) and Embree's BVH; 77–80 bytes measured on the tooth's and
engine CT's levels."""
SCENE_SHARE_OF_MEMORY = 0.25
"""Share of the memory available when a bake starts that its level scenes may hold
(`scene_budget`)."""
REPORT_S = 0.5
"""Seconds between progress-bar updates while a level is traced."""
TEXELS_PER_BATCH = 1 << 20
"""Texels a `ThreadBackend` traces on one level together (`pass_steps`): what bounds a
step's layouts (17 bytes a texel, two steps at a time), and the texels committed together
on their upper level; where the largest levels of a 512³ CT hold tens of millions of
texels."""


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


@dataclass(frozen=True)
class BakeJob:
    """What every pass of one bake traces with, fixed once the plan is made (a new one
    when the lights change: `Baker.relight`).

    Attributes:
        plan: the plan (its records' arrays may be None: `records` holds them).
        records: the plan's texel records (`baking.plan_records`), read a batch at a time.
        tracing: the chunks' constants (`trace_texels` gives each chunk sums of its own;
            its ids are those of the texels a step traces).
        stats: the bake's counters (a backend adds its rays, paths and scene seconds).
    """

    volume: volumes.Volume
    config: BakeConfig
    geometry: LatticeGeometry
    plan: Plan
    records: PlanRecords
    tracing: Tracing
    stats: BakeStats


@dataclass(frozen=True)
class PassWork:
    """What one pass traces (`Baker.pending`).

    Attributes:
        done, remaining: paths done and still to trace by busy texel: (N,) arrays in the
            order of ``groups.members``, or 0-d arrays where they are the same for every
            texel of the plan (a whole bake from scratch holds no per-texel counts);
            uint16 where they fit (`bake._count_type`), else int32.
        first, last: the first and last level the pass traces (`last` = the highest lower
            level + 1).
        groups: the busy texels, those that need paths, by lower level (`LevelGroups`:
            of every plan position in a pass over all, the bake's shared one).
    """

    done: np.ndarray
    remaining: np.ndarray
    first: int
    last: int
    groups: LevelGroups

    @property
    def busy(self) -> np.ndarray | None:
        """(N,) sorted plan positions that need paths, or None: every plan position."""
        return self.groups.members

    def counts(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) paths done and (N,) paths to trace of the busy texels at plan
        `positions`."""
        if self.done.ndim == 0:
            return (np.full(len(positions), self.done, self.done.dtype),
                    np.full(len(positions), self.remaining, self.remaining.dtype))
        at = np.searchsorted(self.busy, positions)
        return self.done[at], self.remaining[at]

    def lower_on(self, level: int) -> np.ndarray:
        """(N,) sorted busy positions whose lower level is `level` (`LevelGroups.of`)."""
        return self.groups.of(level)

    def upper_on(self, level: int) -> np.ndarray:
        """(N,) busy positions whose upper level is `level`: their pass ends with it."""
        if level > self.first:
            return self.lower_on(level - 1)
        return np.zeros(0, index_type(len(self.groups.lower)))


@dataclass(frozen=True)
class PassReport:
    """How a backend reports on a pass to the `Baker` that runs it.

    Attributes:
        commit: ``commit(positions, sums)`` commits the texels at (N,) sorted plan
            `positions` whose pass is done, with their pass sums (`PassSums` of N texels:
            for each texel, 0 + its paths on its lower level + those on its upper one,
            sums formed from zero per chunk) and returns how many had paths; every busy
            texel of the pass is committed once.
        bar: the progress bar (tqdm's ``update`` and ``set_postfix_str``), or None.
        status: ``status(level, note)``, the bar's text while `level` is traced (texels
            done, level, ray rate), with a backend's `note` (e.g. its workers).
    """

    commit: Callable[[np.ndarray, PassSums], int]
    bar: object | None
    status: Callable[[int, str], str]

    def traced(self, paths: int) -> None:
        """Move the bar by `paths` traced paths."""
        if self.bar is not None:
            self.bar.update(paths)

    def show(self, level: int, note: str = "", refresh: bool = False) -> None:
        """Put the status of `level` on the bar."""
        if self.bar is not None:
            self.bar.set_postfix_str(self.status(level, note), refresh=refresh)


class TracingBackend(Protocol):
    """What a `Baker` hands the tracing of its passes to."""

    def begin(self, volume: volumes.Volume, config: BakeConfig,
              kept: np.ndarray | None, stats: BakeStats) -> None:
        """The bake of `config` on `volume` is about to be planned (`kept`: (K,) the levels
        of the lattice it resumes, or None; `stats`: the bake's counters): start what may
        run beside the plan."""

    def levels_known(self, levels: np.ndarray) -> None:
        """The plan's (K,) levels, known before the rest of the plan (`make_plan`'s
        `on_levels`)."""

    def plan_scene(self, level: int) -> Scene | None:
        """The scene of the plan's level `level` (once `levels_known`) for the plan's side
        probes (`make_plan`'s `scenes`), shared with the tracing; None when the backend
        keeps no scenes in this process (the plan then builds its own)."""

    def start(self, job: BakeJob) -> None:
        """Trace with `job` from the next pass on (once the plan is made; again with
        other lights).

        Raises:
            BakeError: the backend cannot trace (e.g. a cluster without workers).
        """

    def trace_pass(self, work: PassWork, report: PassReport) -> None:
        """Trace the pending paths of `work` and commit every busy texel once
        (``report.commit``), with its paths on its lower level added before those on its
        upper one. On an exception, stop what still adds to pass sums before it
        propagates (the Baker keeps the texels committed, drops the others' cut pass)."""

    def record(self, meta: dict[str, Any]) -> None:
        """Add the backend's own counters to the lattice metadata `meta`."""

    def close(self, wait: bool = True) -> None:
        """Stop tracing and let go of threads, processes and connections; without `wait`
        (a Ctrl-C), work still running on a thread is left to end there."""


class PassStep(NamedTuple):
    """One step of a pass (`pass_steps`): `texels` (N,) sorted plan positions traced on
    `level`, their upper level if `upper`, from position `first` of their group on."""

    level: int
    texels: np.ndarray
    upper: bool
    first: int


@dataclass(frozen=True)
class _LevelWork:
    """A `PassStep` laid out: the pending paths of its batch of texels (at most
    `TEXELS_PER_BATCH`) on its level, by texel (numbered as in ``step.texels``), how the
    start points of their texels are made, what its chunks trace with (the batch's ids)
    and the level's scene (None when it has no paths)."""

    step: PassStep
    paths: LevelPaths
    start: LevelStarts
    tracing: Tracing
    scene: Scene | None


def pass_steps(work: PassWork, batch: int) -> Iterator[PassStep]:
    """The order a `ThreadBackend` traces a pass in: one level at a time, lowest first, so
    that a pass traces one level scene at a time. On level l, the texels whose upper level
    it is (``work.upper_on(l)``: traced on l − 1 before, complete here), then those whose
    lower level it is (``work.lower_on(l)``: complete on l + 1), each group a `batch` at a
    time. Yields `PassStep`s."""
    for level in range(work.first, work.last + 1):
        for upper, group in ((True, work.upper_on(level)), (False, work.lower_on(level))):
            for lo in range(0, len(group), batch):
                yield PassStep(level, group[lo:lo + batch], upper, lo)


def scene_budget() -> float:
    """Bytes a bake's level scenes may hold between passes (`ThreadBackend`): a
    `SCENE_SHARE_OF_MEMORY` of the memory available now (2 GB where unknown)."""
    free = available_memory()
    return SCENE_SHARE_OF_MEMORY * (free if free is not None else 8e9)


def scene_bytes(scene: Scene) -> int:
    """Memory `scene` holds, by its triangles (`SCENE_BYTES_PER_TRIANGLE`)."""
    return len(scene.faces) * SCENE_BYTES_PER_TRIANGLE


def warm_up(volume: volumes.Volume) -> None:
    """What a bake needs before it traces and can have while it plans: its compiled code
    loaded (`kernels.warm_up`) and its volume's hash made (cached in the volume)."""
    kernels.warm_up()
    volume.data_hash()


def _helper_thread(workers: int, name: str) -> Executor:
    """One thread beside a bake's `workers` tracing threads, named `name` (in a timeline),
    or (one worker) the caller's own, in turn with the tracing (`cores.Inline`)."""
    return (ThreadPoolExecutor(max_workers=1, thread_name_prefix=name) if workers > 1
            else cores.Inline())


class ThreadBackend:
    """Traces on worker threads of this process, one level at a time and a batch of
    texels at a time on it (`pass_steps`): its paths in chunks of whole texels on a
    thread pool, while a helper thread lays out the next step of the same level. Level
    scenes are cached (least recently used first out): the one level traced, and more
    where successive passes touch the same levels (the lazy viewer's batches); and those
    that fit in `scene_memory` are kept for good, so that the plan's side probes and
    every pass of a bake find them. The next level's is built once the last step on
    this one is done, so a bake with a cache of one and no `scene_memory` holds one
    scene.

    Args:
        workers: threads tracing concurrently (default: CPU count); the result does not
            depend on it.
        scene_cache: level scenes cached whatever their size (at least 1).
        ahead: scenes of the highest levels to build beside the plan (`AHEAD_LEVELS`).
        scene_memory: bytes of level scenes kept for good beside the cache's, by their
            triangles (`scene_bytes`): the first built that fit.
    """

    def __init__(self, workers: int | None = None, scene_cache: int = 1,
                 ahead: int = AHEAD_LEVELS, scene_memory: float = 0.0) -> None:
        self.workers: int = max(1, workers or cores.threads())
        self.job: BakeJob | None = None
        self._pool = cores.executor(self.workers, "isolume-trace")
        # the next step and scenes ahead: on one thread of their own beside the pool, or in
        # turn with the tracing when the bake has one thread; the compiled code's loading on
        # another, so that the first scenes ahead do not queue behind it
        self._helper = _helper_thread(self.workers, "isolume-helper")
        self._warmer = _helper_thread(self.workers, "isolume-warm-up")
        self._scenes: OrderedDict[int, Scene] = OrderedDict()
        self._scene_cache = max(1, scene_cache)
        self._scene_memory = scene_memory
        self._kept: dict[int, Scene] = {}  # scenes kept for good, within `scene_memory`
        self._largest = 0  # bytes of the largest scene built
        self._scene_lock = threading.Lock()
        self._pending: dict[int, cores.Beside] = {}  # scenes being built ahead
        self._ahead = ahead
        self._warm: cores.Beside | None = None
        self._volume: volumes.Volume | None = None
        self._config: BakeConfig | None = None
        self._levels: np.ndarray | None = None
        self._stats: BakeStats | None = None

    def begin(self, volume: volumes.Volume, config: BakeConfig,
              kept: np.ndarray | None, stats: BakeStats) -> None:
        """Load the compiled code, and hash the volume for the lattice's metadata
        (`volumes.Volume.data_hash`: 0.5 s at 512³), on a thread of its own while the plan
        is made (not the helper's: the scenes built ahead would wait for it where the plan
        is quick, on many cores)."""
        self._volume, self._config, self._stats = volume, config, stats
        self._warm = self._beside("warm up", warm_up, volume, on=self._warmer)

    def levels_known(self, levels: np.ndarray) -> None:
        """Build the scenes of the highest `ahead` levels, where the plan's side probes
        start (`sides.choose_sides`), on the helper thread while the plan goes on — or,
        where no side is probed (``sides="normals"``), of the lowest, where the tracing
        starts."""
        self._levels = np.asarray(levels, np.float64)
        count = min(self._ahead, len(levels))
        ahead = (range(count) if self._config.sides == "normals"
                 else range(len(levels) - 1, len(levels) - 1 - count, -1))
        for level in ahead:
            self._pending[level] = self._beside("scene", level_scene, self._volume,
                                                float(levels[level]), self._config)

    def _beside(self, kind: str, function, *args, on: Executor | None = None
                ) -> cores.Beside:
        """`function(*args)` submitted to the helper thread (or `on`), an item of `kind`
        done beside (`cores.submit_beside`)."""
        return cores.submit_beside(on if on is not None else self._helper, kind, function,
                                   *args)

    def plan_scene(self, level: int) -> Scene:
        """The scene of level `level`, from the cache (`_scene`): the plan's side probes
        take the scenes built ahead, and hold no scene beside the cache's."""
        return self._scene(level)

    def start(self, job: BakeJob) -> None:
        """Trace with `job` (once the compiled code is loaded)."""
        if self._warm is not None:
            self._warm.wait()
        self.job = job

    def trace_pass(self, work: PassWork, report: PassReport) -> None:
        """Trace `work` one level at a time and a batch of texels at a time on it
        (`pass_steps`), and commit each batch on its upper level
        (`TracingBackend.trace_pass`). A pass holds one level scene (with a cache of one
        and no `scene_memory`),
        the sums of one group of texels between their two levels (those whose lower level
        was the last traced: 40 bytes a texel in irradiance; two groups' while a level's
        last upper step and first lower one are both queued), at a group's end a copy of
        its last batch's (`TEXELS_PER_BATCH` texels at most) and the layouts of two steps.

        Pipelined within a level: the helper thread lays out the next step while the
        workers trace this one (the chunks run without the GIL); the next step's chunks
        are queued before this one's are collected (its texels are others, its sums other
        rows), so no worker waits for a step's last chunk while the level has work; and a
        batch complete on its upper level is committed (its facings, its means, a
        checkpoint) while the workers trace the next step — also a group's last batch,
        copied out of its sums (one batch's rows) so that the group's sums go once the
        next group's first chunks are queued (both groups' sums are held meanwhile).
        The next level's scene is built once this level's steps are traced, after this
        one is let go (its surface and BVH are built on every core); its first step is
        laid out beforehand, beside this level's last one.
        """
        steps = pass_steps(work, TEXELS_PER_BATCH)  # made as they come: no group held
        step = next(steps, None)
        if step is None:
            return
        channels = self.job.tracing.settings.channels
        chunks: list = []
        between = None  # the sums of the texels whose lower level was the last traced
        traced: list = []  # a batch complete on its upper level, not yet committed
        running: _Running | None = None  # a step of this level, traced beside this one
        try:
            with cores.timed_item("layout"):
                first = self._lay_out(work, step)
            lay = self._waited(self._with_scene, first)
            for following in itertools.chain(steps, [None]):
                step = lay.step
                same_level = following is not None and following.level == step.level
                upcoming = (self._beside("layout", self._lay_out, work, following)
                            if following is not None else None)
                new_group = not step.upper and step.first == 0
                if new_group:  # sums of its own
                    between = PassSums(len(work.lower_on(step.level)), channels)
                sums = between.rows(slice(step.first, step.first + len(step.texels)))
                if running is None:  # the step before was collected: work of its own
                    batch = cores.new_batch()
                chunks = self._submit_level(lay, sums, batch)
                if running is not None:  # the step before, its chunks queued ahead of these
                    self._collect(running.chunks, running.step.level, report)
                    if running.step.upper:
                        traced.append((running.step, running.sums))
                    running = None
                if new_group:
                    # the last group's upper steps are done: its last batch, copied out, is
                    # committed while this step traces, and the group's sums go
                    traced = [(upper_step, done.copy()) for upper_step, done in traced]
                with cores.beside():  # the batch before, while this one is traced
                    _commit(traced, report)
                if same_level:  # traced beside the next step, on the same scene
                    running, chunks = _Running(step, sums, chunks), []
                else:
                    self._collect(chunks, step.level, report)
                    chunks = []
                    if step.upper:
                        traced.append((step, sums))
                if following is not None:
                    if not same_level:  # this level's scene goes before the next one's is built
                        lay = sums = None
                    lay = self._waited(self._with_scene, upcoming.wait())
            _commit(traced, report)
        except BaseException:
            _cancel(chunks + (running.chunks if running is not None else []))
            _commit(traced, report)  # its paths are all traced: it is kept
            raise

    def record(self, meta: dict[str, Any]) -> None:
        """Nothing beyond the Baker's own counters."""

    def close(self, wait: bool = True) -> None:
        """Stop the worker threads and drop the cached scenes; without `wait`, a helper
        still compiling the kernels (the first bake on a machine: seconds) or building a
        scene ahead is left to end on its thread."""
        self._pool.shutdown(wait=wait, cancel_futures=True)
        self._helper.shutdown(wait=wait, cancel_futures=True)
        self._warmer.shutdown(wait=wait, cancel_futures=True)
        self._scenes.clear()
        self._kept.clear()
        self._pending.clear()

    def _scene(self, level: int) -> Scene:
        """The Embree scene of `level`: kept, from the cache, from the scenes built ahead,
        or built now. A scene built is kept for good while it fits in `scene_memory`
        beside those kept (`scene_bytes`), else cached (least recently used out: the cache
        holds at least the level being traced). Passes sweep the levels in turn, so the
        scenes kept are found by every later pass, where a least-recently-used cache of
        fewer scenes than levels would have let each go before it came round again. Room
        is made in the cache before a scene is built — unless one as large as the largest
        built would be kept — so a scene in the making counts against it: a bake with a
        cache of one and no `scene_memory` holds one level scene (`trace_pass` lets the
        traced one go before the next is built). A scene built ahead for a level above
        `level` (one the side probes, going down, found no texel on) goes first, once
        built: it would be a second scene alive."""
        with self._scene_lock:
            if level in self._kept:
                return self._kept[level]
            if level in self._scenes:
                self._scenes.move_to_end(level)
                return self._scenes[level]
            ahead = self._pending.pop(level, None)
            above = [self._pending.pop(k) for k in sorted(self._pending) if k > level]
            if not self._fits(self._largest):
                self._make_room()
        for other in above:
            other.wait()  # its scene built: let go with the future that holds it
        above.clear()
        scene = ahead.wait() if ahead is not None else level_scene(
            self._volume, float(self._levels[level]), self._config)
        with self._scene_lock:
            self._stats.mesh_seconds += scene.mesh_seconds
            self._stats.embree_seconds += scene.build_seconds
            self._stats.scenes += 1
            self._largest = max(self._largest, scene_bytes(scene))
            if self._fits(scene_bytes(scene)):
                self._kept[level] = scene
            else:
                self._make_room()
                self._scenes[level] = scene
        return scene

    def _fits(self, coming: int) -> bool:
        """Whether a scene of `coming` bytes fits in `scene_memory` beside the scenes kept
        (none without a `scene_memory`, empty ones included; call with the lock held)."""
        return self._scene_memory > 0 and (
            sum(map(scene_bytes, self._kept.values())) + coming <= self._scene_memory)

    def _make_room(self) -> None:
        """Let go of the least recently used cached scenes until there is room for one
        more (call with the lock held)."""
        while len(self._scenes) >= self._scene_cache:
            self._scenes.popitem(last=False)

    def _waited(self, function, *args):
        """`function(*args)`, its wall time counted as waiting for level scenes."""
        began = time.perf_counter()
        try:
            return function(*args)
        finally:
            self.job.stats.scene_seconds += time.perf_counter() - began

    def _with_scene(self, lay: _LevelWork) -> _LevelWork:
        """`lay` with its level's scene, where it has paths (built now unless cached)."""
        if not len(lay.paths.texels):
            return lay
        return replace(lay, scene=self._scene(lay.step.level))

    def _lay_out(self, work: PassWork, step: PassStep) -> _LevelWork:
        """Lay out the pending paths of `step` on its isovalue level — its texels'
        upper-level samples if ``step.upper``, else their lower-level ones — sorted by
        texel; its scene is not yet in (`_with_scene`), so that the next level's first
        step is laid out while this level's last one is traced."""
        job = self.job
        records = job.records.of(step.texels)
        done, remaining = work.counts(step.texels)
        batch = np.arange(len(step.texels), dtype=step.texels.dtype)  # into the records
        none = batch[:0]
        paths, start = lay_out_level(
            job.volume, job.geometry, job.config, float(job.plan.levels[step.level]),
            records.ids, records.phase, records.weight, records.high,
            none if step.upper else batch, batch if step.upper else none, done, remaining,
            records.landing)
        return _LevelWork(step, paths, start, replace(job.tracing, ids=records.ids), None)

    def _submit_level(self, lay: _LevelWork, sums: PassSums, batch: int) -> list[Future]:
        """Queue the step's chunks of paths on its scene, items of `batch` in a timeline
        (`cores.new_batch`: the steps of a level queued one beside the next share one,
        their chunks run side by side).

        Workers add their chunks' per-texel sums into the batch's pass sums `sums`: the
        chunks of one step hold disjoint texels, and the batch is committed only after
        its upper level has been collected.
        """
        if len(lay.paths.texels) == 0:
            return []
        return [self._pool.submit(_trace_into, sums, lay, lo, hi, batch)
                for lo, hi in chunk_bounds(lay.paths.counts, self.workers)]

    def _collect(self, chunks: list[Future], level: int, report: PassReport) -> None:
        """Wait for the chunks of `level`; count their paths and rays.

        The progress bar moves every `REPORT_S` seconds and at the end: waking up for
        every finished chunk would take the GIL from the workers a hundred times a level.
        """
        stats = self.job.stats
        pending = set(chunks)
        while pending:
            finished, pending = wait(pending, timeout=REPORT_S)
            for chunk in finished:
                paths, rays, seconds = chunk.result()
                stats.add_rays(rays, seconds)
                stats.paths += paths
                report.traced(paths)
            report.show(level)


def _trace_into(sums: PassSums, lay: _LevelWork, lo: int, hi: int, batch: int
                ) -> tuple[int, int, float]:
    """Trace the paths of the step's texels lo … hi − 1 (`trace_texels`) and add their
    sums to the batch's; returns the paths, the rays and the seconds tracing (an item
    of the timeline's `batch`)."""
    with cores.batch_item(batch, "trace"):
        part, paths, rays, seconds = trace_texels(lay.scene, lay.tracing, lay.paths, lo, hi,
                                                  lay.start)
        sums.add(lay.paths.texels[lo:hi], part)
    return paths, rays, seconds


def _commit(traced: list[tuple[PassStep, PassSums]], report: PassReport) -> None:
    """Commit the batch in `traced` (`report.commit`), taken out first: a commit cut short
    is not made again."""
    while traced:
        step, sums = traced.pop()
        if report.commit(step.texels, sums):  # its facings and means on every core
            report.show(step.level, refresh=True)


class _Running(NamedTuple):
    """A step whose chunks were queued and are not yet collected: its `step`, the `sums`
    its chunks add into and their futures, `chunks`."""

    step: PassStep
    sums: PassSums
    chunks: list[Future]


def _cancel(chunks: list[Future]) -> None:
    """Cancel queued chunks and wait for running ones (they add to a batch's sums)."""
    for chunk in chunks:
        chunk.cancel()
    for chunk in chunks:
        if not chunk.cancelled():
            chunk.exception()
