"""Bakes on a Dask cluster (`distributed`): the same lattice, bit for bit, on many machines.

The machine that runs ``isolume bake --scheduler ADDRESS`` (the *master*) plans the bake,
holds the lattice and the pass sums, and commits texels and saves checkpoints as a local
bake does (`baking.bake.Baker`, whose `TracingBackend` here is `ClusterBackend`). The
tracing runs on the cluster's workers as tasks of (level, group of whole texels):

* What every task needs — the volume, the bake settings, the parsed lighting and the
  tracing constants — is one `_Job`, scattered to every worker once (``broadcast``); a
  task carries only its texels' lattice ids, level phases and weights, samples done and
  still to do (41 bytes per texel) and returns their pass sums ((C + 2) · 8 bytes per
  texel). A worker lays out its texels' paths and start points itself
  (`passes.lay_out_level`), so no path array crosses the network.
* A level scene is built once per worker that traces the level (a per-process cache,
  `_WorkerBake`): each level's tasks prefer one worker (round robin over the workers, a
  loose restriction: Dask's work stealing still moves them to idle workers, which then
  build the scene too), lower levels first (task priority).
* Bit-identical lattices: a task forms its texels' sums from zero (`kernels.accumulate`
  does so locally too: a texel's paths on one level are summed in order, then added to
  its pass sum) and the master adds them to the pass sums level by level (`_LevelSums`:
  a texel's lower-level paths, then its upper-level ones, as a local bake adds them) —
  whatever the workers, the chunking or the completion order.
* A worker that dies costs its unfinished tasks: Dask runs them again elsewhere, and the
  master counts each task's result once (keyed by task). Results from a worker running
  other isolume code or other numerical libraries are refused (`fingerprint`).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import itertools
import logging
import threading
import time
import uuid
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.baking import kernels
from isolume.baking.backend import REPORT_S, BakeJob, BakeStats, PassReport, PassWork, warm_up
from isolume.baking.config import BakeConfig
from isolume.baking.errors import BakeError
from isolume.baking.integrator import PathSettings, TracingLights, WholePaths
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.passes import (
    PassSums,
    Tracing,
    chunk_bounds,
    lay_out_level,
    level_scene,
    stratifies,
    trace_texels,
)
from isolume.volumes import cores

if TYPE_CHECKING:  # Dask is an optional dependency, imported when a cluster is used
    from distributed import Client, LocalCluster

PATHS_PER_TASK = 65536
"""Expected paths per task: ~0.1–0.3 s of tracing, against ~2 ms of Dask overhead."""
RECORDS_AT_ONCE = 1 << 20
"""Texels whose plan records the master reads together to size a level's tasks (25 MB
where a bake keeps them in a file: `baking.plan_records`)."""
LOCAL_PREFIX = "local:"
CONNECT_TIMEOUT_S = 20.0
TASK_TRIES = 3
"""A task Dask cancels (its worker lost with its inputs) is queued at most this often in
all before the bake stops with the cluster's error."""
SCENES_PER_WORKER = 3
"""Level scenes a worker process keeps (its own levels arrive in order; one more for a
stolen task)."""
_LIBRARIES = ("numpy", "numba", "embreex", "scipy", "scikit-image")


@functools.cache
def fingerprint() -> dict[str, str]:
    """What a process's lattice bits depend on: a hash of the isolume code it has loaded
    (every module of `baking` and `volumes`, imported if it is not yet) and the versions
    of the numerical libraries.

    The code is hashed as loaded (bytecode, constants, names), not read from disk again:
    a source file edited after this process imported it would otherwise hash as the
    code this process does not run.
    """
    digest = hashlib.sha256()
    for package in ("baking", "volumes"):
        root = Path(__file__).resolve().parent.parent / package
        for path in sorted(root.glob("*.py")):
            name = f"isolume.{package}" + ("" if path.stem == "__init__" else f".{path.stem}")
            digest.update(name.encode())
            try:
                module = importlib.import_module(name)
            except Exception as exc:  # the same failure on both sides hashes the same
                digest.update(f"import failed: {type(exc).__name__}".encode())
                continue
            _digest_module(module, digest)
    versions = {name: importlib.metadata.version(name) for name in _LIBRARIES}
    return {"isolume code": digest.hexdigest()[:16], **versions}


def _digest_module(module, digest) -> None:
    """Add the code of the functions and classes `module` defines (numba's compiled
    ones by their Python source) and its upper-case constants to `digest`, in name order
    (this module's constants, which size tasks, are left out: they change no bits)."""
    for name, obj in sorted(vars(module).items()):
        if name.isupper() and module.__name__ != __name__:
            if isinstance(obj, np.ndarray):
                digest.update(obj.tobytes())
            elif isinstance(obj, int | float | str | tuple):
                digest.update(f"{name}={obj!r}".encode())
        if getattr(obj, "__module__", None) != module.__name__:
            continue  # imported from elsewhere (hashed there) or data
        members = vars(obj).items() if isinstance(obj, type) else [(name, obj)]
        for member_name, member in sorted(members, key=lambda item: item[0]):
            function = getattr(member, "py_func", None) or getattr(member, "__func__", member)
            code = getattr(function, "__code__", None)
            if code is not None:
                digest.update(f"{name}.{member_name}".encode())
                _digest_code(code, digest)


def _digest_code(code, digest) -> None:
    """Bytecode, names and constants of `code` and of the code nested in it (sets by
    sorted members: their order follows string hashing, which differs between
    processes)."""
    digest.update(code.co_code)
    digest.update(repr(code.co_names).encode())
    for const in code.co_consts:
        if hasattr(const, "co_code"):
            _digest_code(const, digest)
        elif isinstance(const, frozenset):
            digest.update(repr(sorted(map(repr, const))).encode())
        else:
            digest.update(repr(const).encode())


@dataclass(frozen=True)
class _Job:
    """What every task of one bake traces with: scattered to each worker once.

    Attributes:
        token: names this bake in the workers' caches and in task keys.
        fingerprint: the master's `fingerprint()`.
        levels: (K,) isovalues of the plan's levels.
        seed_key, weights, whole: as `passes.Tracing`.
    """

    token: str
    fingerprint: dict[str, str]
    volume: volumes.Volume
    config: BakeConfig
    geometry: LatticeGeometry
    levels: np.ndarray
    lighting: TracingLights
    settings: PathSettings
    seed_key: np.uint32
    weights: np.ndarray
    whole: WholePaths | None


@dataclass(frozen=True)
class _Partial:
    """A task's result: the pass sums of its texels (in its order) and counters.

    Attributes:
        sum: (T, C), second: (T,) float64, n: (T,) int64 — formed from zero.
        paths, rays: traced; trace_seconds: tracing; scene_seconds: building the level
            scene (0 when the worker had it).
    """

    sum: np.ndarray
    second: np.ndarray
    n: np.ndarray
    paths: int
    rays: int
    trace_seconds: float
    scene_seconds: float


class _LevelSums:
    """The master's pass sums of the texels in flight, by lower level: the texels whose
    lower level is l (the sorted plan positions ``work.lower_on(l)``, `PassWork`, kept
    with their sums) sum their paths from their first on level l until they are committed
    with level l + 1, so at most the texels of the levels in flight hold sums, not every
    texel of the plan.

    Args:
        channels: values per texel; work: the pass (its busy texels by lower level,
            `PassWork.lower_on`).
    """

    def __init__(self, channels: int, work: PassWork) -> None:
        self.channels, self.work = channels, work
        self._groups: dict[int, tuple[np.ndarray, PassSums]] = {}

    def add(self, level: int, positions: np.ndarray, upper: np.ndarray,
            sums: PassSums) -> None:
        """Add the sums of paths traced on `level` (formed from zero) of the texels at
        sorted plan `positions` (N,) — (N,) `upper`: the level is their upper one — to
        their running sums."""
        for lower, these in ((level, ~upper), (level - 1, upper)):
            if these.any():
                if lower not in self._groups:
                    group = self.work.lower_on(lower)
                    self._groups[lower] = group, PassSums(len(group), self.channels)
                group, held = self._groups[lower]
                held.add(np.searchsorted(group, positions[these]), sums.rows(these))

    def pop(self, lower: int) -> tuple[np.ndarray, PassSums] | None:
        """The (N,) plan positions of the texels whose lower level is `lower` and their
        sums (None when none of them has paths in the pass), let go of here."""
        return self._groups.pop(lower, None)


# -- worker side ---------------------------------------------------------------------------
_BAKES: dict[str, _WorkerBake] = {}
_BAKES_LOCK = threading.Lock()


class _WorkerBake:
    """One bake's state in a worker process: its job and a few level scenes (least
    recently used first out; each built once, by the first task that needs it)."""

    def __init__(self, job: _Job) -> None:
        differ = [f"{k} {v} here, {job.fingerprint.get(k)} on the master"
                  for k, v in fingerprint().items() if job.fingerprint.get(k) != v]
        if differ:
            raise BakeError("this worker runs other isolume code or libraries than the "
                            f"master ({'; '.join(differ)}): the lattice would not be the "
                            "same bits; install the same isolume and libraries everywhere")
        kernels.warm_up()
        self.job = job
        self._scenes: OrderedDict[int, object] = OrderedDict()
        self._building: dict[int, threading.Lock] = {}
        self._lock = threading.Lock()

    def scene(self, level: int) -> tuple[object, float]:
        """The Embree scene of `level` and the seconds spent building it here (0 when
        cached)."""
        with self._lock:
            building = self._building.setdefault(level, threading.Lock())
        with building:  # a second thread wanting the same level waits for the first
            with self._lock:
                if level in self._scenes:
                    self._scenes.move_to_end(level)
                    return self._scenes[level], 0.0
            t0 = time.perf_counter()
            scene = level_scene(self.job.volume, float(self.job.levels[level]),
                                self.job.config)
            seconds = time.perf_counter() - t0
            with self._lock:
                self._scenes[level] = scene
                while len(self._scenes) > SCENES_PER_WORKER:
                    self._scenes.popitem(last=False)
            return scene, seconds


def _worker_bake(job: _Job) -> _WorkerBake:
    """This process's state for `job` (made by its first task)."""
    with _BAKES_LOCK:
        state = _BAKES.get(job.token)
        if state is None:
            state = _BAKES[job.token] = _WorkerBake(job)
        return state


def forget(token: str) -> None:
    """Drop a finished bake's state from this worker process."""
    with _BAKES_LOCK:
        _BAKES.pop(token, None)


def trace_task(job: _Job, level: int, ids: np.ndarray, phase: np.ndarray,
               weight: np.ndarray, high: np.ndarray, done: np.ndarray,
               remaining: np.ndarray, upper: np.ndarray) -> _Partial:
    """Worker: trace the pending paths of T texels on level `level`.

    Args:
        ids: (T,) sorted flat lattice ids of the texels; phase, weight, high: (T,) their
            plan phases, upper-level weights and lit sides; done, remaining: (T,) int64
            samples they have and still need; upper: (T,) bool, True where `level` is the
            texel's upper level (its samples that go up are traced), False where it is the
            lower.

    Returns:
        the texels' pass sums formed from zero, and counters.
    """
    state = _worker_bake(job)
    job = state.job
    scene, scene_seconds = state.scene(level)
    layout, start = lay_out_level(
        job.volume, job.geometry, job.config, float(job.levels[level]), ids, phase, weight,
        high, np.flatnonzero(~upper), np.flatnonzero(upper), done, remaining)
    acc = PassSums(len(ids), job.settings.channels)
    paths, rays, seconds = 0, 0, 0.0
    if len(layout.texels):
        tracing = Tracing(ids, job.lighting, job.settings, job.seed_key, job.weights,
                          job.whole, stratifies(job.config))
        for lo, hi in chunk_bounds(layout.counts, 1):  # the local bake's chunk sizes
            sums, n, r, t = trace_texels(scene, tracing, layout, lo, hi, start)
            acc.add(layout.texels[lo:hi], sums)
            paths, rays, seconds = paths + n, rays + r, seconds + t
    return _Partial(acc.sum, acc.second, acc.n, paths, rays, seconds, scene_seconds)


# -- master side ---------------------------------------------------------------------------
def connect(scheduler: str, timeout: float = CONNECT_TIMEOUT_S
            ) -> tuple[Client, LocalCluster | None]:
    """A Dask client for `scheduler`: ``tcp://HOST:PORT`` (any address Dask takes) or
    ``local:N`` (a cluster of N single-threaded worker processes on this machine).

    Returns:
        (client, the local cluster or None).

    Raises:
        BakeError: Dask is not installed, `scheduler` is malformed or does not answer.
    """
    try:
        from distributed import Client
    except ImportError:
        raise BakeError(f"--scheduler {scheduler}: needs Dask distributed, an optional "
                        "dependency: pip install 'isolume[cluster]'") from None
    if scheduler.startswith(LOCAL_PREFIX):
        count = scheduler[len(LOCAL_PREFIX):]
        if not count.isdigit() or int(count) < 1:
            raise BakeError(f"--scheduler {scheduler}: expected local:N with N ≥ 1 worker "
                            "processes")
        cluster = local_cluster(int(count))
        return Client(cluster), cluster
    if not scheduler or any(c.isspace() for c in scheduler):
        raise BakeError(f"--scheduler {scheduler!r}: expected a Dask scheduler address "
                        "such as tcp://host:8786, or local:N")
    try:
        return Client(scheduler, timeout=timeout), None
    except (OSError, ValueError, TypeError) as exc:
        raise BakeError(f"--scheduler {scheduler}: no Dask scheduler answered within "
                        f"{timeout:.0f} s ({type(exc).__name__}: {exc})") from None


def local_cluster(workers: int, **options: Any) -> LocalCluster:
    """A ``distributed.LocalCluster`` of `workers` single-threaded worker processes.

    Their nannies give them Dask's usual environment less MALLOC_TRIM_THRESHOLD_: setting
    it also fixes glibc's mmap threshold at 128 kB, so every per-chunk array is mapped and
    unmapped afresh (measured, engine CT, 4 paths/texel, one worker: 8× the page faults,
    system time 0.4 → 2.0 s).
    """
    import dask
    from distributed import LocalCluster

    environ = dask.config.get("distributed.nanny.pre-spawn-environ", {})
    environ = {k: v for k, v in environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            **{"dashboard_address": None, "silence_logs": logging.ERROR,
                               **options})


def task_groups(texels: np.ndarray, expected: np.ndarray,
                paths_per_task: int = PATHS_PER_TASK) -> list[tuple[int, int]]:
    """Cut a level's sorted texels into tasks of about `paths_per_task` expected paths.

    Any cut gives the same lattice (a texel's paths on one level stay in one task); the
    expected counts only size the tasks.

    Args:
        texels: (T,) sorted plan positions; expected: (T,) expected paths of each.

    Returns:
        [(lo, hi)] slices of `texels`, in order, covering them.
    """
    if len(texels) == 0:
        return []
    ends = np.cumsum(expected, dtype=np.float64)
    cuts = np.searchsorted(ends, np.arange(1, int(ends[-1] // paths_per_task) + 1)
                           * float(paths_per_task), side="right")
    bounds = np.unique(np.concatenate([[0], np.minimum(cuts, len(texels) - 1) + 1,
                                       [len(texels)]]))
    return [(int(lo), int(hi)) for lo, hi in itertools.pairwise(bounds)]


@dataclass
class ClusterTraffic:
    """What the cluster did: tasks, bytes each way, scene builds and their seconds."""

    tasks: int = 0
    bytes_sent: int = 0
    bytes_returned: int = 0
    scene_builds: int = 0
    scene_seconds: float = 0.0
    job_bytes: int = 0

    def as_dict(self) -> dict[str, int | float]:
        return {k: float(v) if isinstance(v, float) else int(v)
                for k, v in self.__dict__.items()}


@dataclass
class _Level:
    """A level of the current pass on the cluster: its tasks' texel slices (sorted plan
    positions), whether the level is their upper one, and the tasks' results."""

    texels: list[np.ndarray]
    upper: list[np.ndarray]
    results: dict[int, _Partial]

    @property
    def finished(self) -> bool:
        return len(self.results) == len(self.texels)


@dataclass(frozen=True)
class _Task:
    """One queued task: its level, its index there, `trace_task`'s arguments after the
    level, its try (from 0) and the workers it prefers."""

    level: int
    index: int
    args: tuple
    try_: int
    prefer: list | None


class ClusterBackend:
    """A `TracingBackend` whose paths are traced by tasks on a Dask cluster; the lattice,
    the commits and the checkpoints stay with the `Baker` on this machine.

    Args:
        scheduler: `connect`'s address (``tcp://HOST:PORT`` or ``local:N``).
        client: an existing ``distributed.Client`` instead of `scheduler` (tests,
            benchmarks); it stays open on `close`.

    Raises:
        BakeError: from `connect`.
    """

    def __init__(self, scheduler: str = "", *, client: Client | None = None) -> None:
        self._cluster, self._own_client = None, client is None
        if client is None:
            client, self._cluster = connect(scheduler)
        self.client: Client = client
        self._scheduler = scheduler
        self.traffic: ClusterTraffic = ClusterTraffic()
        self.job: BakeJob | None = None
        self.token: str = ""
        self._scattered = None  # the future of the `_Job` scattered to the workers
        # loads the compiled code beside the plan
        self._helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="isolume-warm-up")
        self._warm: cores.Beside | None = None
        self._worker_list: list[str] = []
        self._workers_asked = -np.inf
        self._threads = 1
        self._passes = 0

    def begin(self, volume: volumes.Volume, config: BakeConfig,
              kept: np.ndarray | None, stats: BakeStats) -> None:
        """Load the compiled code (for the commits) and hash the volume while the plan is
        made (`backend.warm_up`); the workers build the level scenes."""
        self._warm = cores.submit_beside(self._helper, "warm up", warm_up, volume)

    def levels_known(self, levels: np.ndarray) -> None:
        """Nothing: the workers build the level scenes."""

    def plan_scene(self, level: int) -> None:
        """None: the workers' scenes are theirs; the plan builds its own."""

    def start(self, job: BakeJob) -> None:
        """Scatter what every task of `job` needs to every worker (once a worker has
        joined).

        Raises:
            BakeError: no worker joined within `CONNECT_TIMEOUT_S`.
        """
        if self._warm is not None:
            self._warm.wait()
        self._drop_job()
        t = job.tracing
        shared = _Job(uuid.uuid4().hex, fingerprint(), replace(job.volume),  # no caches
                      job.config, job.geometry, np.asarray(job.plan.levels, np.float64),
                      t.lighting, t.settings, t.seed_key, t.weights, t.whole)
        self.token = shared.token
        try:
            self.client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except TimeoutError:
            address = self._scheduler or self.client.scheduler.address
            raise BakeError(f"--scheduler {address}: no worker joined within "
                            f"{CONNECT_TIMEOUT_S:.0f} s (start some with "
                            "`dask worker ADDRESS`)") from None
        self._shared = shared
        self._scattered = self.client.scatter(shared, broadcast=True, hash=False)
        self.traffic.job_bytes = _nbytes(shared)
        self.job = job

    def trace_pass(self, work: PassWork, report: PassReport) -> None:
        """Trace `work` on the cluster (`TracingBackend.trace_pass`): every level's tasks
        may be in flight at once; their pass sums are added and the levels reported done
        in order."""
        from distributed import as_completed

        self._passes += 1  # task keys must not repeat an earlier pass's (Dask reuses results)
        levels: dict[int, _Level] = {}
        sums = _LevelSums(self.job.tracing.settings.channels, work)
        owner: dict = {}  # future -> its _Task
        stream = as_completed()
        next_submit, next_apply = work.first, work.first
        try:
            while next_apply <= work.last:
                while next_submit <= work.last and self._room(levels):
                    levels[next_submit] = self._submit_level_tasks(next_submit, work, owner,
                                                                   stream)
                    next_submit += 1
                if levels[next_apply].finished:
                    self._apply(levels.pop(next_apply), next_apply, sums, report)
                    next_apply += 1
                    continue
                future = next(stream)
                self._receive(future, owner, levels, report, next_apply, stream)
        except BaseException:
            self.client.cancel(list(owner))
            raise

    def record(self, meta: dict[str, Any]) -> None:
        """What moved: ``meta["cluster"]`` (`ClusterTraffic`)."""
        meta["cluster"] = self.traffic.as_dict()

    def close(self, wait: bool = True) -> None:
        """Drop the bake's state on the workers, then the client (and a local cluster);
        without `wait`, the helper loading the kernels is left to end on its thread."""
        self._drop_job()
        if self._own_client:
            self.client.close()
            if self._cluster is not None:
                self._cluster.close()
        self._helper.shutdown(wait=wait, cancel_futures=True)

    def _drop_job(self) -> None:
        """Forget the scattered job on the workers (a cluster already gone has nothing to
        drop)."""
        if self._scattered is None:
            return
        try:
            self.client.cancel([self._scattered])
            self.client.run(forget, self.token)
        except Exception:
            pass
        self._scattered = None

    def _workers(self) -> list[str]:
        """Sorted addresses of the cluster's workers (asked of the scheduler at most
        every `REPORT_S` seconds; their thread count is kept in ``_threads``)."""
        now = time.perf_counter()
        if now - self._workers_asked > REPORT_S:
            info = self.client.scheduler_info(n_workers=-1)["workers"]
            self._worker_list = sorted(info)
            self._threads = sum(int(w.get("nthreads", 1)) for w in info.values())
            self._workers_asked = now
        return self._worker_list

    def _room(self, levels: dict[int, _Level]) -> bool:
        """May another level be submitted? Two levels per worker in flight keep every
        worker on levels it has, and two tasks per thread every thread busy; finished
        levels waiting for an earlier one are held on this machine (their pass sums),
        at most eight per worker."""
        workers = max(1, len(self._workers()))
        unfinished = [level for level in levels.values() if not level.finished]
        tasks = sum(len(level.texels) - len(level.results) for level in unfinished)
        return ((len(unfinished) < 2 * workers or tasks < 2 * self._threads)
                and len(levels) < 8 * workers)

    def _submit_level_tasks(self, level: int, work: PassWork, owner: dict,
                            stream) -> _Level:
        """Queue the tasks of `level`: the lower-level samples of the texels whose lower
        level it is, the upper-level samples of those whose lower level is below it."""
        here = work.lower_on(level)
        texels = np.concatenate([here, work.upper_on(level)])
        order = np.argsort(texels, kind="stable")
        texels = texels[order]
        upper = (np.arange(len(order)) >= len(here))[order]
        expected = np.empty(len(texels))
        for lo in range(0, len(texels), RECORDS_AT_ONCE):  # the records, a batch at a time
            part = slice(lo, lo + RECORDS_AT_ONCE)
            w = self.job.records.of(texels[part]).weight
            expected[part] = work.counts(texels[part])[1] * np.where(upper[part], w, 1.0 - w)
        workers = self._workers()
        prefer = [workers[level % len(workers)]] if workers else None
        slices, uppers = [], []
        for index, (lo, hi) in enumerate(task_groups(texels, expected, PATHS_PER_TASK)):
            part = texels[lo:hi]
            records = self.job.records.of(part)
            done, remaining = work.counts(part)
            args = (records.ids.astype(np.int64), records.phase, records.weight,
                    records.high, done.astype(np.int64), remaining.astype(np.int64),
                    upper[lo:hi])
            self._submit_task(_Task(level, index, args, 0, prefer), owner, stream)
            slices.append(part)
            uppers.append(upper[lo:hi])
        return _Level(slices, uppers, {})

    def _submit_task(self, task: _Task, owner: dict, stream) -> None:
        """Queue one task (`trace_task`), its `try_` in its key (Dask reuses the results
        of a key it has seen)."""
        future = self.client.submit(
            trace_task, self._scattered, task.level, *task.args,
            key=f"isolume-{self.token}-{self._passes}-{task.level}-{task.index}-{task.try_}",
            workers=task.prefer, allow_other_workers=True, priority=-task.level, pure=False)
        owner[future] = task
        stream.add(future)
        self.traffic.tasks += 1
        self.traffic.bytes_sent += sum(a.nbytes for a in task.args)

    def _resubmit(self, future, task: _Task, owner: dict, stream) -> bool:
        """Queue a task that Dask cancelled (a worker lost in flight can take a task's
        inputs with it) once more, with the job scattered again if its copies are gone;
        False after `TASK_TRIES` tries."""
        if future.status != "cancelled" or task.try_ + 1 >= TASK_TRIES:
            return False
        if self._scattered.status != "finished":
            self._scattered = self.client.scatter(self._shared, broadcast=True, hash=False)
        self._submit_task(_Task(task.level, task.index, task.args, task.try_ + 1,
                                task.prefer), owner, stream)
        return True

    def _receive(self, future, owner: dict, levels: dict[int, _Level], report: PassReport,
                 next_apply: int, stream) -> None:
        """Take one finished task's result (once per task, whatever Dask re-ran)."""
        task = owner.pop(future)
        level, index = task.level, task.index
        try:
            part: _Partial = future.result()
        except BakeError:
            raise
        except Exception as exc:
            if self._resubmit(future, task, owner, stream):
                return
            raise BakeError(f"cluster task {future.key} failed on the cluster: "
                            f"{type(exc).__name__}: {exc}") from None
        results = levels[level].results
        if index in results:
            return
        results[index] = part
        stats = self.job.stats
        stats.add_rays(part.rays, part.trace_seconds)
        stats.paths += part.paths
        stats.scene_seconds += part.scene_seconds
        self.traffic.bytes_returned += part.sum.nbytes + part.second.nbytes + part.n.nbytes
        self.traffic.scene_builds += part.scene_seconds > 0
        self.traffic.scene_seconds += part.scene_seconds
        if report.bar is not None:
            report.traced(part.paths)
            report.show(next_apply, f"{len(self._workers())} workers ")

    def _apply(self, finished: _Level, level: int, sums: _LevelSums,
               report: PassReport) -> None:
        """Add a finished level's task sums to the pass sums `sums` (in the order a local
        bake adds them in), then commit the texels whose upper level it is."""
        for index, part in sorted(finished.results.items()):
            sums.add(level, finished.texels[index], finished.upper[index],
                     PassSums.of(part.sum, part.second, part.n))
        complete = sums.pop(level - 1)
        if complete is not None:
            report.commit(*complete)


def _nbytes(obj) -> int:
    """Pickled size of `obj` (what scattering it sends to each worker)."""
    import pickle

    return len(pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))
