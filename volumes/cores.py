"""The cores a command may use: how many, one pool of threads over them, and a timeline of
where they go.

A command says once how many threads it may keep busy (`use`, from its ``--workers``);
whatever runs in parallel asks `threads()`: the compiled kernels of the fields and the
plan (`for_ranges`, `for_items` on the one pool), the side probes, the tracing chunks,
Embree's BVH builds (`embree_threads`), Mesa's llvmpipe (``LP_NUM_THREADS``, read when a
GL context is made) and BLAS (threadpoolctl). By default it is the cores this process
may run on — its CPU affinity, and a cgroup's CPU quota where one is set — not the
machine's count (`available`).

`for_items(work, count)` hands the items 0 … count − 1 out one at a time to the pool's
threads and to the calling thread, which works too: no item waits for a thread while the
caller idles, a slow item (a cluster of stalled Newton points) holds up one thread, not a
share of the work, and a call made on a pool thread (nested) cannot deadlock (the caller
alone can finish every item). Each item writes its own part of the result, so any split
and any order give the same bits.

A `Timeline` (``--timeline FILE.json``) records, per stage of a fixed list (`STAGES`),
the wall time, every thread's CPU time from the OS (``/proc/self/task/*/schedstat``,
child processes from ``/proc`` and `resource`) — not the intervals of tasks, which count
a thread waiting for the GIL as busy — the seconds with at most one core busy (sampled),
the peak resident memory, the CPU seconds other processes used on the same cores and
those the hypervisor stole from them (``/proc/stat``), the process's kernel time, page
faults and context switches (`usage.ProcessCounters`: where CPU time that grows with
the threads goes), and the work items with their
threads and durations (`app.bench.replay` replays them on more simulated threads than
this machine has). Work
that a command does beside its critical path — the next step laid out, a level scene
built ahead, a batch committed while the next one is traced — runs inside `beside()`:
its items are marked so, and the replay lets them share the threads of the work that
follows instead of running between it and the work before.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

from isolume.volumes import usage
from isolume.volumes.errors import IsolumeError, interrupted_by
from isolume.volumes.writing import atomic_write

_T = TypeVar("_T")

STAGES = (
    "load",
    "texel values",
    "gradients",
    "levels",
    "paths onto levels",
    "seen sides",
    "reach tests",
    "settle",
    "tracing",
    "save",
    "surface",
    "seen surface",
    "nearest points",
    "framing",
    "level scenes",
    "draw",
)
"""The named stages a timeline records, in the order a bake (load … save) and a render
(load, surface … tracing, draw) pass through them; a stage may be skipped or visited
again (each visit is recorded on its own)."""
MIN_COST = 1 << 11
"""Least work of one item of `for_ranges`, in units of its ``cost_per_item`` (a point of
a compiled kernel: about a microsecond): a few milliseconds, against ~0.1 ms of handing
an item out, so that a short call — a level's marching cubes on the tooth CT, 30 ms —
still has an item for each of 16 threads (with 16 k it has two, and the replay of the
tooth's bake on 16 threads gives ×10.3 against ×11.6; two-thread walls alike within their
noise)."""
ITEMS_PER_CALL = 64
"""Items a large `for_ranges` call is cut into, at least (and 8 per thread): no item is
more than 1/64 of the call, so the last one holds up no thread for long."""
BLOCKS = 256
"""Blocks a `for_blocks` call cuts its elements into where its largest block allows: no
block is more than 1/64 of the call's work, and a block of slow elements (stalled Newton
points cluster in space) holds up one thread."""
MIN_BLOCK = 1024
"""Fewest elements of a block (the numpy between a block's kernels costs ~0.1 ms)."""
GLUE_BLOCK = 8192
"""Fewest elements of a block of a call whose work is mostly numpy on (N, 8)-sized rows (a
bake's fills, judgements and commits): its calls hold the GIL between array operations
that release it, and blocks of fewer rows hand the GIL from thread to thread (a context
switch each) for little work: the tooth CT's default bake makes 9–11 k voluntary context
switches on two threads with blocks of 8192, 24–26 k with 1024, and its wall is 2.3 %
shorter there and 1.6 % on one (medians of paired runs), for 4 % more peak memory."""
SAMPLE_S = 0.05
"""Seconds between a timeline's readings of every thread's CPU time."""
STOP_WAIT_S = 0.5
"""Seconds a Ctrl-C waits for the items of a `for_items` call still running before it goes
on: one that is loading or compiling its kernel (the first run on a machine compiles for
seconds) is left to end on its pool thread; the call's work is abandoned with it."""
SERIAL_CORES = 1.1
"""A sampled interval counts as serial when the threads' CPU time in it is at most this
many times its length (at most one core busy, with the noise of a waking thread)."""


class CoresError(IsolumeError):
    """A thread count that cannot be used (less than one)."""


def available() -> int:
    """The cores this process may run on: its CPU affinity (``taskset``, a container's
    cpuset), further bounded by a cgroup v2 CPU quota (``cpu.max``) where one is set."""
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        count = os.cpu_count() or 1
    quota = _cgroup_quota()
    return max(1, min(count, quota) if quota else count)


def cgroup_file(name: str) -> str | None:
    """The text of this process's cgroup v2 control file `name` (e.g. ``cpu.max``,
    ``memory.max``), or None where there is no such cgroup or it cannot be read."""
    try:
        with open("/proc/self/cgroup") as f:
            path = next((line.strip().split("::", 1)[1] for line in f
                         if line.startswith("0::")), None)
        if path is None:
            return None
        with open(Path("/sys/fs/cgroup") / path.lstrip("/") / name) as f:
            return f.read()
    except OSError:
        return None


def _cgroup_quota() -> int | None:
    """Cores of this process's cgroup v2 CPU quota (``cpu.max``: quota and period in µs,
    rounded up), or None where there is none or it cannot be read."""
    text = cgroup_file("cpu.max")
    if text is None:
        return None
    try:
        quota, period = text.split()[:2]
        return None if quota == "max" else max(1, math.ceil(int(quota) / int(period)))
    except ValueError:  # not two numbers
        return None


class _Cores:
    """The process's thread count and its one pool (made on first use, remade when the
    count changes)."""

    def __init__(self) -> None:
        self.count = available()
        self.lock = threading.Lock()
        self.pool: ThreadPoolExecutor | None = None
        self.pool_size = 0
        self.blas = None  # threadpoolctl's limits, held while they apply


_CORES = _Cores()
_LOCAL = threading.local()  # .pooled: this thread is one of the pool's


def use(workers: int | None) -> int:
    """Let this process keep `workers` threads busy (None: `available()`), everywhere: the
    pool, Embree's builds, llvmpipe's rasterizer threads (a GL context made from now on),
    the BLAS libraries loaded (at most `workers` threads, never more than they had:
    `_limit_blas`; the command line loads them with one thread, `app.blas`, and a BLAS
    loaded later, SciPy's, keeps the one). Returns the count. Raises CoresError below 1."""
    count = available() if workers is None else int(workers)
    if count < 1:
        raise CoresError(f"--workers {workers}: expected at least 1")
    with _CORES.lock:
        _CORES.count = count
    os.environ["LP_NUM_THREADS"] = str(count if count > 1 else 0)
    _limit_blas(count)
    return count


def threads() -> int:
    """How many threads this process may keep busy (`use`)."""
    return _CORES.count


def embree_threads() -> int:
    """Threads an Embree device may build with (its ``threads=`` configuration)."""
    return _CORES.count


def _limit_blas(count: int) -> None:
    """Hold the BLAS and OpenMP libraries loaded to at most `count` threads each
    (threadpoolctl, where it is installed), never to more than they started with:
    isolume's own work runs on its pool, where a BLAS grown to N threads would only start
    them — each spinning ~0.1 s as it starts, 15 cores' worth in the first stage of a
    16-thread command — and share them among the pool's concurrent calls."""
    try:
        from threadpoolctl import threadpool_info, threadpool_limits
    except ImportError:
        return
    if _CORES.blas is not None:
        _CORES.blas.restore_original_limits()
    held: dict[str, int] = {}
    for library in threadpool_info():  # by prefix: copies of one library share their limit
        prefix = library["prefix"]
        held[prefix] = min(held.get(prefix, count), library["num_threads"])
    _CORES.blas = threadpool_limits(limits=held)


def pool() -> ThreadPoolExecutor:
    """The process's pool of `threads()` threads (kept across calls)."""
    with _CORES.lock:
        if _CORES.pool is None or _CORES.pool_size != _CORES.count:
            if _CORES.pool is not None:
                _CORES.pool.shutdown(wait=False)
            _CORES.pool = ThreadPoolExecutor(max_workers=_CORES.count,
                                             thread_name_prefix="isolume-core",
                                             initializer=pool_thread)
            _CORES.pool_size = _CORES.count
        return _CORES.pool


def pool_thread() -> None:
    """Mark the calling thread as one of a pool's that keeps a core busy (the initializer
    of such pools): the `for_items` it calls run on it alone, not on more threads."""
    _LOCAL.pooled = True


def in_pool() -> bool:
    """Is the calling thread one of a pool's (`pool_thread`)?"""
    return getattr(_LOCAL, "pooled", False)


def executor(workers: int, name: str) -> ThreadPoolExecutor | Inline:
    """A pool of `workers` threads marked `pool_thread` (its own, for work queued apart
    from `for_items`: tracing chunks), or, for one, `Inline`: work runs as it is submitted,
    on the submitting thread, so that a single-threaded command keeps one core busy."""
    if workers <= 1:
        return Inline()
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name,
                              initializer=pool_thread)


class Inline:
    """An executor that runs each function when it is submitted, on the caller's thread
    (`executor` for one worker)."""

    def submit(self, function: Callable[..., _T], /, *args: Any, **kwargs: Any) -> Future[_T]:
        """Run `function(*args, **kwargs)` now; a finished Future of its result."""
        future: Future[_T] = Future()
        try:
            future.set_result(function(*args, **kwargs))
        except Exception as error:
            future.set_exception(error)
        return future

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        """Nothing to stop."""


class _Items:
    """Items 0 … count − 1 of one `for_items` call, handed out one at a time to whichever
    thread asks (``next`` on a shared counter is atomic under the GIL)."""

    def __init__(self, work: Callable[[int], None], count: int, kind: str) -> None:
        self.work, self.count, self.kind = work, count, kind
        self.next = itertools.count()
        self.active = 0
        self.done = 0
        self.stopped = False
        self.error: BaseException | None = None
        self.cond = threading.Condition()
        self.batch = next(_BATCHES)
        self.beside = getattr(_LOCAL, "beside", False)  # the caller's, for every thread

    def run(self, on_done: Callable[[int], None] | None = None) -> None:
        """Take and run items until none is left (or the call stopped); `on_done(done)`
        after each of this thread's items."""
        with self.cond:
            self.active += 1
        nested = getattr(_LOCAL, "pooled", False)
        _LOCAL.pooled = True  # what an item calls in parallel runs on this thread
        try:
            while not self.stopped:
                i = next(self.next)
                if i >= self.count:
                    break
                with _item(self.batch, self.kind, self.beside):
                    self.work(i)
                with self.cond:
                    self.done += 1
                if on_done is not None:
                    on_done(self.done)
        except BaseException as error:
            self.error = self.error or error
            self.stopped = True
            raise
        finally:
            _LOCAL.pooled = nested
            with self.cond:
                self.active -= 1
                self.cond.notify_all()

    def helper(self) -> None:
        """A pool thread's share (errors reach the caller through `error`)."""
        try:
            self.run()
        except BaseException:
            return

    def finish(self) -> None:
        """Wait until no thread runs an item of this call; re-raise a helper's error."""
        with self.cond:
            while self.active:
                self.cond.wait()
        if self.error is not None:
            raise self.error


_BATCHES = itertools.count()


def for_items(work: Callable[[int], None], count: int, kind: str = "",
              on_done: Callable[[int], None] | None = None,
              workers: int | None = None) -> None:
    """`work(i)` for i in 0 … count − 1 on the pool's threads and the caller's, an item at a
    time to whichever is free (see the module docstring), on at most `workers` threads
    (None: `threads()`); `on_done(done)` is called on the calling thread after each of
    its items and once all are done (progress: rising, ending at `count`). Returns when
    every item is done; an error in any item stops the handing out, waits for the items
    running and is raised. A Ctrl-C in the caller waits for them `STOP_WAIT_S` at most:
    an item still running then (one compiling its kernel) ends on its pool thread, its
    work abandoned, so a caller that lets go of what its items use after an interrupt
    (a file they write) keeps them from it. `kind` names the items in a timeline."""
    if count <= 0:
        return
    items = _Items(work, count, kind)
    wanted = threads() if workers is None else min(max(1, workers), threads())
    helpers = 0 if in_pool() else min(wanted, count) - 1
    if helpers > 0:
        executor = pool()
        for _ in range(helpers):
            executor.submit(items.helper)
    told = [0]

    def tell(done: int) -> None:
        told[0] = done
        on_done(done)

    try:
        items.run(tell if on_done is not None else None)
    except BaseException as error:
        items.stopped = True
        _finish_quietly(items, STOP_WAIT_S if interrupted_by(error) else None)
        raise
    items.finish()
    if on_done is not None and told[0] < count:  # the last items ran on other threads
        on_done(count)


def _finish_quietly(items: _Items, at_most: float | None = None) -> None:
    """Wait for the items still running after the caller's error (they are short), for at
    most `at_most` seconds (None: until they end)."""
    deadline = None if at_most is None else time.monotonic() + at_most
    with items.cond:
        while items.active and (deadline is None or time.monotonic() < deadline):
            items.cond.wait(0.1)


def item_bounds(count: int, cost_per_item: int) -> list[tuple[int, int]]:
    """(lo, hi) ranges cutting [0, count) into items of at least `MIN_COST` work (each of
    the `count` elements costing `cost_per_item`), at least `ITEMS_PER_CALL` and 8 per
    thread where the work allows, of equal size to within one."""
    most = max(1, count * max(1, cost_per_item) // MIN_COST)
    pieces = max(1, int(min(count, most, max(ITEMS_PER_CALL, 8 * threads()))))
    cuts = [count * k // pieces for k in range(pieces + 1)]
    return list(itertools.pairwise(cuts))


def for_ranges(work: Callable[[int, int], None], count: int, cost_per_item: int = 1,
               kind: str = "") -> None:
    """`work(lo, hi)` over [0, count) in the ranges of `item_bounds`, by `for_items`."""
    bounds = item_bounds(count, cost_per_item)
    if len(bounds) == 1 or threads() == 1 or in_pool():
        with _item(next(_BATCHES), kind):
            work(0, count)
        return
    for_items(lambda i: work(*bounds[i]), len(bounds), kind)


def blocks(count: int, largest: int, least: int = MIN_BLOCK) -> list[slice]:
    """Slices of `count` elements, in order: `BLOCKS` of them, of at least `least` and
    at most `largest` elements (fewer where `count` is small)."""
    size = max(1, min(largest, max(least, -(-count // BLOCKS))))
    return [slice(lo, min(lo + size, count)) for lo in range(0, count, size)]


def for_blocks(work: Callable[[slice], None], count: int, largest: int, kind: str = "",
               progress: Callable[[float], None] | None = None,
               least: int = MIN_BLOCK) -> None:
    """`work(block)` for each slice of `blocks(count, largest, least)` by `for_items`;
    `progress` told the fraction of blocks done, on the calling thread."""
    parts = blocks(count, largest, least)
    told = (None if progress is None
            else lambda done: progress(min(1.0, done / len(parts))))
    for_items(lambda b: work(parts[b]), len(parts), kind, on_done=told)


# --- the timeline -------------------------------------------------------------------------


class Timeline:
    """Where a command's cores go, stage by stage (see the module docstring). `stage(name)`
    ends the stage in progress and begins `name` (one of `STAGES`); `finish()` ends the
    last and returns the record (`save` writes it as JSON)."""

    def __init__(self, sample_s: float = SAMPLE_S) -> None:
        self.began: float = time.perf_counter()
        self.sample_s: float = sample_s
        self.stages: list[dict[str, Any]] = []
        self.items: list[tuple[int, int, str, float, float, bool]] = []
        self.names: dict[int, str] = {}
        self.samples: list[tuple[float, dict[int, float]]] = []
        self._open: dict[str, Any] | None = None
        self._stop = threading.Event()
        self._own: int | None = None  # the sampler's thread, whose CPU is not the command's
        self._seen: dict[int, float] = {}
        self._rss: list[tuple[float, int]] = []  # (time, resident bytes) sampled
        self._sampler = threading.Thread(target=self._sample, name="isolume-timeline",
                                         daemon=True)
        self._sampler.start()  # last: it sets `_own` as it begins

    def _sample(self) -> None:
        self._own = threading.get_native_id()
        while not self._stop.wait(self.sample_s):
            reading = usage.thread_cpu()
            now = self._now()
            self.samples.append((now, reading))
            self._rss.append((now, usage.resident_bytes()))
            self._seen.update(reading)

    def _threads_cpu(self) -> dict[int, float]:
        """Every thread's CPU seconds now; for a thread that has ended, its last sampled
        figure (a pool shut down before its stage ends)."""
        return {**self._seen, **usage.thread_cpu()}

    def _now(self) -> float:
        return time.perf_counter() - self.began

    def stage(self, name: str) -> None:
        """End the stage in progress and begin `name`."""
        if name not in STAGES:
            raise ValueError(f"timeline stage {name!r}: expected one of {', '.join(STAGES)}")
        self._end()
        self._open = {"name": name, "start_s": self._now(), "cpu": self._threads_cpu(),
                      "children": usage.children_cpu(), "machine": usage.machine_cpu(available()),
                      "counters": usage.process_counters()}

    def _end(self) -> None:
        if self._open is None:
            return
        opened, self._open = self._open, None
        end, cpu, children = self._now(), self._threads_cpu(), usage.children_cpu()
        counted = usage.process_counters().since(opened["counters"])
        machine, machine0 = usage.machine_cpu(available()), opened["machine"]
        per_thread = {tid: seconds - opened["cpu"].get(tid, 0.0)
                      for tid, seconds in cpu.items() if tid != self._own}
        per_thread = {tid: s for tid, s in per_thread.items() if s > 0.0005}
        own = sum(per_thread.values()) + children - opened["children"]
        self.stages.append({
            "name": opened["name"], "start_s": opened["start_s"], "end_s": end,
            "wall_s": end - opened["start_s"],
            "cpu_s": own,
            "others_cpu_s": (None if machine is None or machine0 is None
                             else max(0.0, machine[0] - machine0[0] - own)),
            "stolen_s": None if machine is None or machine0 is None else machine[1] - machine0[1],
            "threads_cpu_s": {str(t): s for t, s in sorted(per_thread.items())},
            "children_cpu_s": children - opened["children"],
            "rss_mb": max([usage.resident_bytes(), *(b for t, b in self._rss
                                                if opened["start_s"] <= t <= end)]) / 2**20,
            **counted._asdict(),
        })

    def item(self, batch: int, kind: str, began: float, ended: float,
             beside: bool = False) -> None:
        """Record one work item that ran on the calling thread (`beside`: off the
        critical path, see the module docstring)."""
        tid = threading.get_native_id()
        self.names.setdefault(tid, threading.current_thread().name)
        self.items.append((batch, tid, kind, began - self.began, ended - self.began, beside))

    def finish(self) -> dict[str, Any]:
        """End the last stage and the sampling; the record (see `summary`)."""
        self._end()
        self._stop.set()
        self._sampler.join()
        return self.summary()

    def summary(self) -> dict[str, Any]:
        """The record: the stages (wall, CPU, per-thread CPU, the CPU seconds other
        processes used on this process's cores as ``others_cpu_s`` and the hypervisor took
        from them as ``stolen_s`` (`usage.machine_cpu`; None where it cannot tell), serial
        seconds, the highest resident memory sampled in them as ``rss_mb``, the process's
        own kernel time, page faults and context switches in them (the fields of
        `usage.ProcessCounters`: ``user_s``, ``system_s``, ``minor_faults``, …), items:
        ``[batch, thread, kind, start_s, end_s]`` and a sixth element 1 for an item done
        beside), the sampled busy cores, the threads' names, the process's peak resident
        memory (MiB)."""
        busy = _busy_cores(self.samples, self._own)
        # an item belongs to the stage it began in, or, begun between two stages (a
        # stage's counters are read as it ends and the next begins: ~10 ms in which a
        # helper thread may start work), to the one after
        ends = [-math.inf] + [stage["end_s"] for stage in self.stages]
        for k, stage in enumerate(self.stages):
            inside = [(t, dt, cores) for t, dt, cores in busy
                      if stage["start_s"] < t <= stage["end_s"]]
            stage["serial_s"] = min(stage["wall_s"], sum(dt for _, dt, c in inside
                                                         if c <= SERIAL_CORES))
            stage["items"] = [[b, tid, kind, round(s, 6), round(e, 6), *([1] if side else [])]
                              for b, tid, kind, s, e, side in self.items
                              if ends[k] <= s < ends[k + 1]]
        return {
            "threads": threads(), "available_cores": available(),
            "load_average": list(os.getloadavg()),
            "wall_s": self._now(), "sample_s": self.sample_s,
            "peak_rss_mb": usage.peak_resident_bytes() / 2**20,
            "stages": self.stages,
            "busy": [[round(t, 4), round(c, 3)] for t, _, c in busy],
            "thread_names": {str(t): n for t, n in self.names.items()},
        }


def _busy_cores(samples: list[tuple[float, dict[int, float]]], own: int | None
                ) -> list[tuple[float, float, float]]:
    """(end time, length, cores busy) of each interval between two samples: the threads'
    CPU seconds in it (the sampler's own left out) over its length."""
    out = []
    for (t0, a), (t1, b) in itertools.pairwise(samples):
        dt = t1 - t0
        if dt <= 0:
            continue
        cpu = sum(seconds - a.get(tid, 0.0) for tid, seconds in b.items() if tid != own)
        out.append((t1, dt, cpu / dt))
    return out


_TIMELINE: Timeline | None = None


def stage(name: str) -> None:
    """Begin stage `name` of the timeline being recorded (nothing when none is)."""
    if _TIMELINE is not None:
        _TIMELINE.stage(name)


@contextmanager
def _item(batch: int, kind: str, beside: bool | None = None) -> Iterator[None]:
    """Record the work inside as an item of `batch` in the timeline being recorded, unless
    it runs inside another item (whose time holds it already); `beside` (None: whether
    this thread is inside `beside()`) marks it off the critical path."""
    depth = getattr(_LOCAL, "depth", 0)
    _LOCAL.depth = depth + 1
    began = time.perf_counter()
    try:
        yield
    finally:
        _LOCAL.depth = depth
        if _TIMELINE is not None and depth == 0:
            side = getattr(_LOCAL, "beside", False) if beside is None else beside
            _TIMELINE.item(batch, kind, began, time.perf_counter(), side)


def timed_item(kind: str) -> AbstractContextManager[None]:
    """A context that records the work inside as one item of the timeline, a batch of its
    own (a scene build, a commit, a chunk of paths)."""
    return _item(next(_BATCHES), kind)


def new_batch() -> int:
    """A batch id for items recorded one at a time (`batch_item`) that may run side by
    side, as a `for_items` call's do."""
    return next(_BATCHES)


def batch_item(batch: int, kind: str) -> AbstractContextManager[None]:
    """A context that records the work inside as one item of `batch` (`new_batch`)."""
    return _item(batch, kind)


@contextmanager
def beside() -> Iterator[None]:
    """Mark the work inside, and the `for_items` calls it makes, as done beside the
    critical path (see the module docstring): the next step prepared while this one
    runs."""
    before = getattr(_LOCAL, "beside", False)
    _LOCAL.beside = True
    try:
        yield
    finally:
        _LOCAL.beside = before


def beside_call(kind: str, function: Callable[..., _T], /, *args: Any,
                batch: int | None = None) -> _T:
    """`function(*args)` inside `beside()`, recorded as one item of `kind` (what a command
    submits to a helper thread, or, with one thread, runs in turn), of `batch` where the
    command waits for it by that id (`waited`)."""
    with beside(), _item(next(_BATCHES) if batch is None else batch, kind):
        return function(*args)


def waited(future: Future[_T], batch: int) -> _T:
    """`future`'s result, the point where a command needs the work it submitted as
    `beside_call(..., batch=batch)` marked in the timeline (an item of kind "wait" and no
    length): the replay lets that work run beside everything before this point."""
    result = future.result()
    if _TIMELINE is not None:
        now = time.perf_counter()
        _TIMELINE.item(batch, "wait", now, now)
    return result


class Beside(NamedTuple):
    """Work submitted beside the critical path (`submit_beside`), waited for later: its
    `future` and its `batch` in a timeline."""

    future: Future
    batch: int

    def wait(self) -> Any:
        """The work's result (`waited`: the timeline marks where it was needed)."""
        return waited(self.future, self.batch)

    def cancel(self) -> bool:
        """Drop the work if no thread has begun it; whether it was dropped."""
        return self.future.cancel()


def submit_beside(executor: Executor, kind: str, function: Callable[..., Any], /,
                  *args: Any) -> Beside:
    """`function(*args)` submitted to `executor` as `beside_call`, an item of `kind`."""
    batch = new_batch()
    return Beside(executor.submit(beside_call, kind, function, *args, batch=batch), batch)


def ahead(kind: str, function: Callable[..., Any], /, *args: Any) -> Beside | None:
    """`submit_beside` to the pool where a thread can be spared for work that the caller
    needs later: with more than one thread, called from outside the pool (whose threads
    may all be busy with the caller's own items). None elsewhere: do the work when it is
    needed."""
    if threads() > 1 and not in_pool():
        return submit_beside(pool(), kind, function, *args)
    return None


@contextmanager
def recording(path: str | os.PathLike[str] | None, **about: Any) -> Iterator[Timeline | None]:
    """Record a timeline of the work inside into `path` (JSON, with `about`: the command,
    its arguments) — also when the work fails or is interrupted; nothing when `path` is
    None."""
    global _TIMELINE
    if path is None:
        yield None
        return
    timeline = Timeline()
    timeline.stage("load")
    _TIMELINE = timeline
    try:
        yield timeline
    finally:
        _TIMELINE = None
        record = {**about, **timeline.finish()}
        atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(record)), "timeline")
