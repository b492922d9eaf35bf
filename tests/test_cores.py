"""The cores a command uses (`volumes.cores`): the count, the pool's items, the timeline,
and `--workers 1` keeping one core busy in every stage (the OS's own CPU counters)."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from isolume.volumes import cores, usage

CLI = "import sys; from isolume.app.cli import main; sys.exit(main())"


@pytest.fixture
def three_threads():
    cores.use(3)
    try:
        yield
    finally:
        cores.use(None)


def test_available_cores_follow_the_affinity():
    """A process pinned to one core (``taskset``) may use one, whatever the machine has."""
    code = ("import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
            "from isolume.volumes import cores; print(cores.available(), cores.threads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["1", "1"]
    assert cores.available() == len(os.sched_getaffinity(0))


@pytest.mark.parametrize("files, cores_of, memory_left", [
    ({"cpu.max": "150000 100000\n", "memory.max": "8000000000\n",
      "memory.current": "3000000000\n"}, 2, 5_000_000_000),
    ({"cpu.max": "max 100000\n", "memory.max": "max\n", "memory.current": "1\n"},
     None, None),
    ({"memory.max": "100\n", "memory.current": "200\n"}, None, 0),
    ({}, None, None)])
def test_a_containers_cgroup_limits_cores_and_memory(monkeypatch, files, cores_of,
                                                     memory_left):
    """A cgroup v2 CPU quota rounds up to whole cores; its memory limit caps the memory
    the bake's budgets read (`available_memory`: the least of the machine's and the
    cgroup's); no file, no limit."""
    from isolume.volumes.io import common

    monkeypatch.setattr(cores, "cgroup_file", files.get)
    monkeypatch.setattr(common, "cgroup_file", files.get)
    monkeypatch.setattr(common, "_machine_memory", lambda: 6_000_000_000)  # MemAvailable
    assert cores._cgroup_quota() == cores_of
    assert common.cgroup_memory_left() == memory_left
    machine = 6_000_000_000
    assert common.available_memory() == (
        machine if memory_left is None else min(machine, memory_left))


def test_a_thread_count_below_one_is_refused():
    with pytest.raises(cores.CoresError, match="--workers 0: expected at least 1"):
        cores.use(0)


def test_every_item_runs_once_on_several_threads(three_threads):
    """Items are handed out one at a time: each runs once, on more than one thread where
    they take a while, and progress is told on the calling thread only."""
    ran = np.zeros(200, np.int64)
    names, told = set(), []
    caller = threading.get_ident()

    def work(i: int) -> None:
        ran[i] += 1
        names.add(threading.get_ident())
        time.sleep(0.002)

    cores.for_items(work, len(ran), on_done=lambda done: told.append(
        (done, threading.get_ident() == caller)))
    assert (ran == 1).all()
    assert len(names) > 1
    assert all(on_caller for _, on_caller in told)
    done = [d for d, _ in told]
    assert done == sorted(set(done)) and done[-1] == len(ran)


def test_a_nested_call_runs_on_its_item_thread(three_threads):
    """An item that itself asks for items (a Newton step inside a plan block) gets them on
    its own thread: no oversubscription, no deadlock when every pool thread does it."""
    outer = np.zeros((12, 50), np.int64)

    def item(i: int) -> None:
        me = threading.get_ident()
        seen = set()

        def inner(j: int) -> None:
            seen.add(threading.get_ident())
            outer[i, j] += 1

        cores.for_items(inner, outer.shape[1])
        assert seen == {me}

    cores.for_items(item, len(outer))
    assert (outer == 1).all()


def test_an_error_in_an_item_stops_the_call_and_reaches_the_caller(three_threads):
    started = []

    def work(i: int) -> None:
        started.append(i)
        if i == 5:
            raise ValueError("item 5")
        time.sleep(0.001)

    with pytest.raises(ValueError, match="item 5"):
        cores.for_items(work, 10_000)
    assert len(started) < 10_000


@pytest.mark.parametrize("error", [KeyboardInterrupt, ValueError])
def test_ctrl_c_waits_at_most_stop_wait_s_for_an_item_still_running(three_threads, error):
    """A Ctrl-C in the caller leaves an item still running after `cores.STOP_WAIT_S` (one
    compiling its kernel) to end on its pool thread, and raises; any other error waits for
    the running items to end."""
    helper_busy, release = threading.Event(), threading.Event()
    caller = threading.current_thread()

    def work(i: int) -> None:
        if threading.current_thread() is caller:
            assert helper_busy.wait(5)
            raise error("stop")
        helper_busy.set()
        release.wait(5)

    hold = cores.STOP_WAIT_S + 1.0
    timer = threading.Timer(hold, release.set)
    timer.start()
    began = time.perf_counter()
    try:
        with pytest.raises(error, match="stop"):
            cores.for_items(work, 2)
        took = time.perf_counter() - began
    finally:
        release.set()
        timer.cancel()
    if error is KeyboardInterrupt:
        assert cores.STOP_WAIT_S - 0.05 <= took < cores.STOP_WAIT_S + 0.5
    else:
        assert took >= hold - 0.05


@pytest.mark.parametrize("count,cost", [(10, 1), (5000, 1), (1_000_000, 1), (300, 10_000)])
def test_ranges_cover_the_work_in_small_items(count, cost):
    """`item_bounds` cuts [0, count) exactly, into pieces of at least `MIN_COST` work, and
    into at least `ITEMS_PER_CALL` where the work allows: none above 1/64 of the call."""
    bounds = cores.item_bounds(count, cost)
    assert bounds[0][0] == 0 and bounds[-1][1] == count
    assert all(a[1] == b[0] for a, b in itertools.pairwise(bounds))
    sizes = np.array([hi - lo for lo, hi in bounds])
    assert sizes.max() - sizes.min() <= 1
    if count * cost >= cores.ITEMS_PER_CALL * cores.MIN_COST:
        assert len(bounds) >= cores.ITEMS_PER_CALL and sizes.max() <= -(-count // 64)
    else:
        assert sizes.min() * cost >= cores.MIN_COST or len(bounds) == 1


@pytest.mark.parametrize("count,least", [(100, cores.MIN_BLOCK), (300_000, cores.MIN_BLOCK),
                                         (300_000, cores.GLUE_BLOCK),
                                         (5_000_000, cores.GLUE_BLOCK)])
def test_blocks_cover_the_elements_between_their_least_and_largest_sizes(count, least):
    """`blocks` cuts [0, count) in order into `BLOCKS` slices where each then holds at
    least `least` elements and at most `largest`, else into fewer of `least` each."""
    largest = 1 << 16
    parts = cores.blocks(count, largest, least)
    assert parts[0].start == 0 and parts[-1].stop == count
    assert all(a.stop == b.start for a, b in itertools.pairwise(parts))
    sizes = np.array([p.stop - p.start for p in parts])
    assert sizes.max() <= largest and (sizes[:-1] >= min(least, count)).all()
    assert len(parts) <= cores.BLOCKS or sizes.max() == largest
    if count == 300_000:  # 256 blocks of 1172, or 37 of the glue's 8192
        assert len(parts) == (cores.BLOCKS if least == cores.MIN_BLOCK else 37)


def test_for_ranges_gives_the_same_result_on_any_thread_count():
    data = np.random.default_rng(3).random(300_000)
    outs = []
    for threads in (1, 2, 5):
        cores.use(threads)
        out = np.empty_like(data)

        def part(lo: int, hi: int, out=out) -> None:
            out[lo:hi] = np.sqrt(data[lo:hi]) * 3.0

        try:
            cores.for_ranges(part, len(data), 1)
        finally:
            cores.use(None)
        outs.append(out)
    for out in outs[1:]:
        np.testing.assert_array_equal(out, outs[0])


def test_a_timeline_records_stages_cpu_and_items(tmp_path, three_threads):
    """Stages in order with their wall and CPU seconds (the OS's per-thread counters: a
    busy thread's CPU shows, a sleeping one's does not), and the items run."""
    path = tmp_path / "t.json"

    def spin(_i: int) -> None:
        end = time.thread_time() + 0.02
        while time.thread_time() < end:
            pass

    with cores.recording(path, command=["test"]):
        cores.for_items(spin, 30, "spin")
        cores.stage("save")
        time.sleep(0.3)
    record = json.loads(path.read_text())
    names = [s["name"] for s in record["stages"]]
    assert names == ["load", "save"] and record["command"] == ["test"]
    load, save = record["stages"]
    assert len(load["items"]) == 30 and {i[2] for i in load["items"]} == {"spin"}
    assert load["cpu_s"] >= 30 * 0.02 * 0.9
    assert save["wall_s"] >= 0.29 and save["cpu_s"] < 0.1
    assert save["serial_s"] >= 0.2  # nothing busy: at most one core
    with pytest.raises(ValueError, match="timeline stage 'nowhere'"):
        cores.Timeline().stage("nowhere")


def test_an_item_begun_between_two_stages_belongs_to_the_next():
    """A stage's counters are read as it ends and the next begins; work a helper thread
    starts in between (a flood beside the plan) belongs to the stage after, and work
    begun before the first stage to the first: no item is lost from the timeline."""
    timeline = cores.Timeline()
    try:
        timeline.stage("load")
        timeline.stage("texel values")
        gap_from = timeline.stages[0]["end_s"]
        timeline._open["start_s"] = gap_from + 0.010  # a gap of 10 ms, as reading can take
        timeline.item(7, "box reach", timeline.began + gap_from + 0.005,
                      timeline.began + gap_from + 0.5, beside=True)
        timeline.item(8, "warm up", timeline.began - 0.001, timeline.began + 0.1, beside=True)
        time.sleep(0.05)  # the second stage ends after its item began
    finally:
        record = timeline.finish()
    load, values = record["stages"]
    assert [item[0] for item in load["items"]] == [8]
    assert [item[0] for item in values["items"]] == [7]


def test_a_timeline_marks_work_done_beside_and_records_memory(tmp_path, three_threads):
    """Items of `beside()` work — its own and its `for_items` calls' on other threads —
    carry the mark; the others do not; each stage holds the highest resident memory
    sampled in it, at least what an array it allocates and touches takes."""
    path = tmp_path / "t.json"
    with cores.recording(path):
        cores.for_items(lambda _i: time.sleep(0.01), 6, "plain")
        with cores.beside():
            cores.for_items(lambda _i: time.sleep(0.01), 6, "commit")
        cores.beside_call("layout", time.sleep, 0.01)
        cores.stage("tracing")
        big = np.ones(64 << 20, np.uint8)  # 64 MiB, touched
        time.sleep(0.2)
        alive = usage.resident_bytes() / 2**20
        del big
    record = json.loads(path.read_text())
    load, tracing = record["stages"]
    marked = {item[2]: len(item) > 5 and item[5] == 1 for item in load["items"]}
    assert marked == {"plain": False, "commit": True, "layout": True}
    assert len([i for i in load["items"] if i[2] == "commit"]) == 6
    assert tracing["rss_mb"] >= alive - 1 and alive > 64
    assert record["peak_rss_mb"] >= tracing["rss_mb"] - 1


def test_a_timeline_counts_kernel_time_page_faults_and_waits(tmp_path):
    """Per stage, the OS's counts for the process: first touching 128 MiB of fresh memory
    faults its pages in (at least one fault per 2 MiB, the largest page); ten sleeps are
    at least ten waits; a stage that touches nothing new faults less than the one that
    does. (The kernel time is not bounded below: where the OS splits CPU time into user
    and kernel by sampling ticks, a tenth of a second of faults may read as none.)"""
    path = tmp_path / "t.json"
    with cores.recording(path):
        cores.stage("tracing")
        touched = np.empty(128 << 20, np.uint8)
        touched.fill(1)
        cores.stage("save")
        for _ in range(10):
            time.sleep(0.01)
        del touched
    tracing, save = _stages(path)[1:]
    assert set(usage.ProcessCounters._fields) <= set(tracing)
    assert tracing["minor_faults"] >= 64
    assert save["voluntary_switches"] >= 10
    assert save["minor_faults"] < tracing["minor_faults"]
    assert all(stage[c] >= 0 for stage in (tracing, save) for c in usage.ProcessCounters._fields)


@pytest.mark.skipif(usage.machine_cpu(cores.available()) is None or os.getpid() == 1,
                    reason="no /proc/stat for this process's cores, or pytest reaps orphans")
def test_a_timeline_counts_what_other_processes_use_on_its_cores(tmp_path):
    """A stage in which another process on the same cores burns 0.5 s of CPU while this
    one waits records that CPU as the other processes' (the machine's counters, ticks of
    0.01 s), not as its own — a child process's is its own; the whole command's figures
    add it up. (Only lower bounds on the others': the machine runs other work too.)"""
    from isolume.app.bench.cores import whole

    path = tmp_path / "t.json"
    burn = ("import time\nend = time.process_time() + 0.5\n"
            "while time.process_time() < end:\n    pass\n")
    with cores.recording(path):
        cores.stage("tracing")
        subprocess.run([sys.executable, "-c", burn], check=True)  # a child: its own work
    tracing = json.loads(path.read_text())["stages"][-1]
    assert tracing["children_cpu_s"] >= 0.45 and tracing["cpu_s"] >= 0.45
    with cores.recording(path):
        cores.stage("tracing")
        _burn_elsewhere(burn, tmp_path / "done")
    tracing = json.loads(path.read_text())["stages"][-1]
    assert tracing["cpu_s"] < 0.2 and tracing["others_cpu_s"] >= 0.4
    assert tracing["stolen_s"] >= 0.0
    assert whole(json.loads(path.read_text()), 2.0)["others_cpu_s"] >= 0.4


def _burn_elsewhere(code: str, done: Path) -> None:
    """Run `code` in a process that is not this one's child (a double fork: the middle
    process exits at once) and wait, at most a minute, for `done` to appear after it."""
    launcher = (f"import os, subprocess, sys\nif os.fork() == 0:\n    try:\n"
                f"        subprocess.run([sys.executable, '-c', {code!r}])\n    finally:\n"
                f"        open({str(done)!r}, 'w').close()\n        os._exit(0)\n")
    subprocess.run([sys.executable, "-c", launcher], check=True)
    deadline = time.monotonic() + 60
    while not done.exists():
        assert time.monotonic() < deadline, "the process burning CPU did not finish"
        time.sleep(0.02)


def _stages(path) -> list[dict]:
    return json.loads(path.read_text())["stages"]


@pytest.mark.parametrize("command", ["bake", "render"])
def test_one_worker_keeps_one_core_busy_in_every_stage(tmp_path, command):
    """``--workers 1``: in every stage, the CPU time of all the process's threads (tracing,
    Embree's builds, Mesa's rasterizer, BLAS) is at most 1.05 × its wall time (and 5 ms:
    the threads' counters are read one after another at a stage's two ends)."""
    timeline = tmp_path / "t.json"
    out = tmp_path / ("l.npz" if command == "bake" else "p.png")
    args = [command, "synthetic:engine:72", "--workers", "1", "--samples", "8",
            "--out", str(out), "--timeline", str(timeline)]
    if command == "render":
        args += ["--size", "256x256"]
    subprocess.run([sys.executable, "-c", CLI, *args], check=True, capture_output=True)
    stages = _stages(timeline)
    assert {"paths onto levels", "seen sides", "tracing", "save"} <= {s["name"] for s in stages} \
        if command == "bake" else {"surface", "tracing", "draw"} <= {s["name"] for s in stages}
    for stage in stages:
        if stage["wall_s"] > 0.05:
            assert stage["cpu_s"] <= 1.05 * stage["wall_s"] + 0.005, stage["name"]
            assert len(stage["threads_cpu_s"]) >= 1
    if command == "render":  # the GL drawing is an item the replay scales as measured
        drawn = {s["name"] for s in stages for item in s["items"] if item[2] == "gl"}
        assert {"seen surface", "draw"} <= drawn


def test_ctrl_c_stops_a_bake_within_two_seconds_in_the_plan(tmp_path):
    """SIGINT in the middle of the plan's stages (the side probes on every core) ends the
    command within 2 s with exit status 130."""
    timeline = tmp_path / "t.json"
    proc = subprocess.Popen([sys.executable, "-c", CLI, "bake", "synthetic:engine:160",
                             "--samples", "64", "--out", str(tmp_path / "l.npz"),
                             "--timeline", str(timeline)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(4.5)  # the side probes, on a quiet 2-core machine
    sent = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=10)
    finally:
        proc.kill()
    assert time.perf_counter() - sent < 2.0
    assert proc.returncode == 130
    assert timeline.exists()  # the timeline is written when the command is interrupted


def test_ctrl_c_stops_a_bake_within_two_seconds_while_its_kernels_compile(tmp_path):
    """The first bake on a machine compiles its kernels (an empty numba cache: ~40 s here),
    on the pool's threads and the helper beside the plan, and no Ctrl-C cuts a kernel's
    compilation: SIGINT then still ends the command within 2 s with exit status 130 (the
    threads left compiling, not waited for), and writes no lattice."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    out = tmp_path / "l.npz"
    proc = subprocess.Popen([sys.executable, "-c", CLI, "bake", "synthetic:engine:72",
                             "--out", str(out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(4.0)  # compiling: the plan's kernels, and the tracer's beside them
    sent = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert time.perf_counter() - sent < 2.0, err
    assert proc.returncode == 130, err
    assert "interrupted" in err and not out.exists()


def test_the_command_line_loads_blas_with_one_thread_and_use_never_grows_it():
    """Importing the command line starts no BLAS thread (one spins ~0.1 s as it starts, on a
    core a ``--workers 1`` command does not hold), and `cores.use` keeps the loaded BLAS at
    its one thread; a BLAS the environment starts with more (two: OpenBLAS takes no more
    than the machine's cores) is held to one by ``cores.use(1)`` and back to what it
    started with, not eight, by ``cores.use(8)``."""
    from isolume.app import blas

    script = ("import os, json; import isolume.app.cli; from isolume.volumes import cores; "
              "from threadpoolctl import threadpool_info; "
              "count = lambda: sorted({i['num_threads'] for i in threadpool_info()}); "
              "first = (len(os.listdir('/proc/self/task')), count()); cores.use(N); "
              "held = count(); cores.use(8); "
              "print(json.dumps([first, held, count()]))")
    env = {k: v for k, v in os.environ.items() if k not in blas.THREAD_VARIABLES}
    done = subprocess.run([sys.executable, "-c", script.replace("N", "2")], env=env,
                          check=True, capture_output=True, text=True)
    (tasks, loaded), held, eight = json.loads(done.stdout)
    assert tasks == 1 and loaded == [1]
    assert held == [1] and eight == [1]
    env.update(dict.fromkeys(blas.THREAD_VARIABLES, "2"))
    done = subprocess.run([sys.executable, "-c", script.replace("N", "1")], env=env,
                          check=True, capture_output=True, text=True)
    (_, loaded), held, eight = json.loads(done.stdout)
    assert held == [1] and eight == loaded


def test_numba_loads_its_array_maths_without_scipy_and_dot_still_compiles():
    """The console script's start (`app.blas.numba_without_blas_probe`) leaves SciPy's
    linear algebra unloaded as numba readies a kernel (0.12 s and 30–50 MB of a command's
    start),
    leaves no hidden module behind, and compiled ``np.dot`` still loads SciPy's BLAS and
    gives the product; a process that has SciPy's BLAS already keeps numba's answer."""
    script = ("import sys, json, numba, numpy as np; from isolume.app import blas; "
              "PRE; blas.numba_without_blas_probe(); "
              "from numba.np import arraymath; "
              "f = numba.njit(lambda a: a.sum() * 2.0); f(np.ones(3)); "
              "before = ['scipy.linalg' in sys.modules, arraymath._HAVE_BLAS, "
              "'scipy.linalg.cython_blas' in sys.modules]; "
              "dot = numba.njit(lambda a, b: np.dot(a, b)); "
              "a = np.arange(6.0).reshape(2, 3); "
              "ok = bool(np.array_equal(dot(a, a.T), a @ a.T)); "
              "print(json.dumps([before, ok]))")
    done = subprocess.run([sys.executable, "-c", script.replace("PRE", "pass")],
                          check=True, capture_output=True, text=True)
    assert json.loads(done.stdout) == [[False, False, False], True]
    done = subprocess.run([sys.executable, "-c", script.replace(
        "PRE", "import scipy.linalg.cython_blas")], check=True, capture_output=True, text=True)
    assert json.loads(done.stdout) == [[True, True, True], True]
