"""``isolume bench cores``: the replay scheduler, Amdahl's law and the aggregation on
hand-made timelines, the child runs, and one small run end to end (no timed assertions)."""

from __future__ import annotations

import json
import sys

import pytest
from PIL import Image

from isolume.app.bench.cores import (
    aggregate,
    amdahl,
    command_argv,
    default_threads,
    median_run,
    predictions,
    run_child,
    run_name,
    sameness_line,
    stage_labels,
    thread_counts,
    whole,
)
from isolume.app.bench.counters import COUNTERS, counters_line
from isolume.app.bench.replay import (
    inner_factors,
    makespan,
    replay,
    replay_stage,
    split_hints,
    thinned,
    work_units,
)
from isolume.app.bench.stalls import tracing_stalls
from isolume.app.cli import main
from isolume.app.options import CLIError


def _stage(name, start, wall, items, cpu=None, serial=0.0):
    """A timeline stage; `items`: (batch, tid, kind, start, end)."""
    return {"name": name, "start_s": start, "end_s": start + wall, "wall_s": wall,
            "cpu_s": wall if cpu is None else cpu, "serial_s": serial,
            "items": [list(item) for item in items]}


def _timeline(stages, threads=1, wall=None):
    return {"threads": threads, "stages": stages,
            "wall_s": wall if wall is not None else sum(s["wall_s"] for s in stages)}


def _batch(batch, kind, start, seconds, tid=1):
    """Items of one batch run back to back on thread `tid` from `start`."""
    items, t = [], start
    for s in seconds:
        items.append((batch, tid, kind, t, t + s))
        t += s
    return items


def test_greedy_list_scheduling_in_recorded_order():
    # A: 4, then 1 (free at 4 before B at 5); B: 3, then 2 -> both end at 5
    assert makespan([4, 3, 2, 1], 2) == pytest.approx(5)
    assert makespan([4, 3, 2, 1], 1) == pytest.approx(10)
    assert makespan([4, 3, 2, 1], 64) == pytest.approx(4)  # the largest item
    # in order, not sorted: the 5 comes last and lands on a thread already busy for 2
    assert makespan([1, 1, 1, 1, 5], 2) == pytest.approx(7)
    assert makespan([], 8) == 0


def test_a_stage_replays_as_glue_plus_batches_one_after_another():
    items = _batch(1, "newton", 0.0, [4, 3, 2, 1]) + _batch(2, "settle", 10.0, [2, 2])
    stage = _stage("paths onto levels", 0.0, 16.0, items)  # 14 s of items, 2 s of glue
    assert replay_stage(stage, 1) == pytest.approx(16)
    assert replay_stage(stage, 2) == pytest.approx(2 + 5 + 2)
    assert replay_stage(stage, 64) == pytest.approx(2 + 4 + 2)


def test_consecutive_single_items_of_one_kind_run_together():
    # three trace chunks (a batch each), a commit, one more chunk
    items = [(7, 1, "trace", 0, 3), (8, 1, "trace", 3, 6), (9, 1, "trace", 6, 9),
             (10, 1, "commit", 9, 10), (11, 1, "trace", 10, 12)]
    assert work_units(items) == [[3, 3, 3], [1], [2]]
    assert replay_stage(_stage("tracing", 0, 12, items), 4) == pytest.approx(3 + 1 + 2)
    # a batch between two singles of one kind keeps them apart
    items = [(1, 1, "trace", 0, 1), *_batch(2, "surface", 1, [1, 1]), (3, 1, "trace", 3, 4)]
    assert work_units(items) == [[1], [1, 1], [1]]


def test_a_whole_single_item_is_cut_as_the_run_with_more_threads_cut_it():
    one = _timeline([_stage("texel values", 0, 10, [(1, 1, "grid values", 0, 10)])])
    assert replay(one, 64)["texel values"] == pytest.approx(10)  # no hint: one item
    # two threads cut the same call into 5 items, the last half of the work
    two = _timeline([_stage("texel values", 0, 4, _batch(5, "grid values", 0, [1, 1, 1, 1, 4])
                            + _batch(6, "grid values", 0, [1, 1], tid=2))], threads=2)
    hints = split_hints(two)
    assert hints[("texel values", "grid values")][0] == pytest.approx([.125] * 4 + [.5])
    assert replay(one, 64, hints)["texel values"] == pytest.approx(5)
    assert replay(one, 2, hints)["texel values"] == pytest.approx(2.5 + 5)  # A: 1.25 × 2 + 5
    assert replay(one, 1, hints)["texel values"] == pytest.approx(10)


def test_the_whole_command_replays_its_stages_and_the_time_outside_them():
    stages = [_stage("load", 0, 1, []),
              _stage("paths onto levels", 1, 12, _batch(1, "newton", 1, [4, 3, 2, 1])),
              _stage("tracing", 13, 6, [(2, 1, "trace", 13, 16), (3, 1, "trace", 16, 19)])]
    one = _timeline(stages, wall=20)  # 1 s outside the stages
    at2 = replay(one, 2)
    assert at2["paths onto levels"] == pytest.approx(2 + 5)
    assert at2["tracing"] == pytest.approx(3)
    assert at2["whole"] == pytest.approx(1 + 7 + 3 + 1)
    assert replay(one, 1)["whole"] == pytest.approx(20)


def test_work_done_beside_shares_the_threads_of_the_work_it_overlapped():
    # one thread records a step's chunks, then the batch before committed beside them
    # (1 s each), then the next step's chunks; a commit before any unit of its visit
    # waits for the next one
    items = [*[(*item, 1) for item in _batch(1, "commit", 0, [2])],
             *_batch(2, "trace", 2, [3, 3]),
             *[(*item, 1) for item in _batch(3, "commit", 8, [1, 1])],
             (4, 1, "trace", 10, 13)]
    assert work_units(items) == [[2, 3, 3, 1, 1], [3]]
    stage = _stage("tracing", 0, 13, items)
    assert replay_stage(stage, 1) == pytest.approx(13)
    assert replay_stage(stage, 2) == pytest.approx(5 + 3)  # (2, 3 | 3, 1, 1) then 3
    assert replay_stage(stage, 3) == pytest.approx(4 + 3)  # (2, 1, 1 | 3 | 3) then 3
    # a commit left at a visit's start with nothing before it waits for the next stage's work
    sides = _stage("seen sides", 0, 2, [(6, 1, "commit", 0, 2, 1)])
    tracing = _stage("tracing", 2, 4, _batch(7, "trace", 2, [2, 2]))
    at2 = replay(_timeline([sides, tracing]), 2)
    assert at2["seen sides"] == pytest.approx(0)
    assert at2["tracing"] == pytest.approx(4)  # (2, 2, 2) on two threads
    # and left at the very end, it runs on its own
    assert replay(_timeline([sides]), 2)["seen sides"] == pytest.approx(2)


def test_work_waited_for_by_name_runs_on_a_lane_of_its_own_until_then():
    """Loading the compiled code (6 s, beside) while the plan runs; the tracing waits for
    it: on eight threads the plan's 8 s take 1 s (and 6/8 s of the lane's share), the
    tracing waits until 6 s, then takes 2 s."""
    warm = (9, 1, "warm up", 0, 6, 1)
    one = _timeline([
        _stage("load", 0, 6, [warm]),
        _stage("texel values", 6, 8, _batch(1, "grid values", 6, [1] * 8)),
        _stage("tracing", 14, 16, [(9, 1, "wait", 14, 14), *_batch(2, "trace", 14, [1] * 16)]),
    ])
    assert replay(one, 1)["whole"] == pytest.approx(30)
    at8 = replay(one, 8)
    assert at8["load"] == pytest.approx(0.75) and at8["texel values"] == pytest.approx(1)
    assert at8["tracing"] == pytest.approx(6 - 1.75 + 2)
    assert at8["whole"] == pytest.approx(8)
    assert aggregate(one)["tracing"]["items"] == 16  # the mark is no work item


def test_a_scene_built_ahead_does_not_wait_for_the_warm_up_on_its_lane():
    """The compiled code loads beside (6 s, on a thread of its own) from the start; two
    scenes are built ahead (2 s each, beside, on the helper thread) once the levels are
    known, the first waited for by the side probes, the second by the tracing. On eight
    threads the first is issued at 0.75 s and done at 2.75 s — not after the warm-up, at
    8 s — the second after it; the tracing still waits for the warm-up (6 s)."""
    one = _timeline([
        _stage("load", 0, 6, [(9, 1, "warm up", 0, 6, 1)]),
        _stage("levels", 6, 12, [*_batch(1, "levels", 6, [1] * 8),
                                 (12, 1, "scene", 14, 16, 1), (13, 1, "scene", 16, 18, 1)]),
        _stage("seen sides", 18, 8, [(12, 1, "wait", 18, 18),
                                     *_batch(2, "side probes", 18, [1] * 8)]),
        _stage("tracing", 26, 8, [(9, 1, "wait", 26, 26), (13, 1, "wait", 26, 26),
                                  *_batch(3, "trace", 26, [1] * 8)]),
    ])
    assert replay(one, 1)["whole"] == pytest.approx(34)
    at8 = replay(one, 8)
    assert at8["load"] == pytest.approx(0.75)
    assert at8["levels"] == pytest.approx(1 + 2 * 2 / 8)  # the scenes' share of the cores
    assert at8["seen sides"] == pytest.approx(2.75 - 2.25 + 1)
    assert at8["tracing"] == pytest.approx(6 - 3.75 + 1)
    assert at8["whole"] == pytest.approx(7)  # on one lane with the warm-up: 11


def test_work_done_beside_a_unit_is_issued_where_that_unit_began():
    """A level's next step laid out (1 s, beside, on the calling thread) while the workers
    trace this one (a batch of 16 items of 1 s); the command waits for it after queueing
    the next step's chunks in the same batch, then traces the next level (8 items). On
    eight threads the layout starts with the batch and is done at 1 s, long before the
    batch's 2 s end: no wait, only its share of the cores (1/8 s) — where issued after the
    batch it would make the tracing wait until 3 s."""
    items = [*_batch(2, "trace", 0, [1] * 8, tid=2), (7, 1, "layout", 3, 4, 1),
             (7, 1, "wait", 4, 4), *_batch(2, "trace", 8, [1] * 8, tid=2),
             *_batch(3, "trace", 16, [1] * 8, tid=2)]
    stage = _stage("tracing", 0, 24, items)
    assert replay_stage(stage, 8, laned=frozenset({7})) == pytest.approx(2 + 1 / 8 + 1)
    assert replay_stage(stage, 1, laned=frozenset({7})) == pytest.approx(24 + 1)
    before = [*_batch(2, "trace", 1, [1] * 16, tid=2), (7, 1, "layout", 0, 1, 1),
              (7, 1, "wait", 17, 17), *_batch(3, "trace", 17, [1] * 8, tid=2)]
    stage = _stage("tracing", 0, 25, before)  # laid out before the batch: in order
    assert replay_stage(stage, 8, laned=frozenset({7})) == pytest.approx(1 / 8 + 2 + 1)


def test_short_gaps_between_a_units_items_are_the_items_own_overhead():
    # four probe items with 1 ms between them (a progress update after each), then 0.5 s of
    # glue (a scene let go) before the next level's items
    items = [(1, 1, "side probes", t, t + 1) for t in (0, 1.001, 2.002, 3.003)]
    items += [(2, 1, "side probes", t, t + 1) for t in (4.503, 5.504)]
    stage = _stage("seen sides", 0, 6.504, items)
    units = work_units(items)
    assert [len(unit) for unit in units] == [4, 2]
    assert sum(units[0]) == pytest.approx(4.003) and sum(units[1]) == pytest.approx(2.001)
    assert replay_stage(stage, 1) == pytest.approx(6.504)  # one thread: the run itself
    assert replay_stage(stage, 4) == pytest.approx(0.5 + 1.001 + 1.001)


def test_an_item_parallel_inside_is_shortened_as_it_scaled_when_measured():
    # a BVH build: 8 s on one thread, 5 s on two -> serial fraction (2·5/8 − 1)/(2 − 1) = 0.25
    one = _timeline([_stage("tracing", 0, 8, [(1, 1, "bvh", 0, 8)])])
    two = _timeline([_stage("tracing", 0, 5, [(1, 1, "bvh", 0, 5)])], threads=2)
    inner = inner_factors(one, two)
    assert inner["bvh"] == pytest.approx(0.25)
    assert replay(one, 2, inner=inner)["tracing"] == pytest.approx(5)
    assert replay(one, 16, inner=inner)["tracing"] == pytest.approx(8 * (0.25 + 0.75 / 16))
    assert replay(one, 16)["tracing"] == pytest.approx(8)  # without the fit: serial
    assert inner_factors(one, one)["bvh"] == 1.0  # no run with more threads: serial
    slower = _timeline([_stage("tracing", 0, 9, [(1, 1, "bvh", 0, 9)])], threads=2)
    assert inner_factors(one, slower)["bvh"] == 1.0  # clamped
    assert predictions(one, two)["tracing"]["replay"]["2"] == pytest.approx(8 / 5)


def test_checkpoints_come_as_often_as_the_predicted_wall_time_allows():
    """A bake saves a checkpoint every 60 s at most: one thread made three in 200 s of
    tracing; on two threads (100 s) there is room for one, on sixteen for none."""
    items, t = [], 0.0
    for k in range(100):
        items.append((k, 1, "trace", t, t + 2))
        t += 2
        if k in (29, 59, 89):
            items.append((1000 + k, 1, "checkpoint", t, t + 1, 1))
            t += 1
    one = _timeline([_stage("tracing", 0, t, items)])
    assert replay(one, 1)["whole"] == pytest.approx(203)
    assert replay(one, 2)["whole"] == pytest.approx(30 + 71)  # the first kept: 30 | 1 + 70
    assert replay(one, 16)["whole"] == pytest.approx(14)  # 100 items of 2 s: 7 rounds
    fewer = thinned(one, 1)
    assert fewer["wall_s"] == pytest.approx(201)
    assert [i[2] for i in fewer["stages"][0]["items"]].count("checkpoint") == 1


def test_amdahl():
    assert amdahl(10, 2, 4) == pytest.approx(10 / (2 + 8 / 4))
    assert amdahl(10, 0, 64) == pytest.approx(64)
    assert amdahl(10, 10, 64) == pytest.approx(1)
    assert amdahl(10, 12, 16) == pytest.approx(1)  # serial clamped to the whole
    assert amdahl(0, 0, 16) == 1.0


def test_repeated_visits_add_up_by_name():
    timeline = _timeline([
        _stage("seen sides", 0, 2, _batch(1, "side probes", 0, [0.5, 0.5]), cpu=3, serial=1),
        _stage("tracing", 2, 4, _batch(2, "trace", 2, [1, 3]), cpu=6, serial=0.5),
        _stage("seen sides", 6, 1, _batch(3, "side probes", 6, [0.2, 0.6]), cpu=1.5,
               serial=0.25),
    ], threads=2)
    figures = aggregate(timeline)
    assert list(figures) == ["seen sides", "tracing"]
    sides = figures["seen sides"]
    assert sides["visits"] == 2 and sides["items"] == 4
    assert sides["wall_s"] == pytest.approx(3) and sides["cpu_s"] == pytest.approx(4.5)
    assert sides["serial_s"] == pytest.approx(1.25)
    assert sides["item_s"] == pytest.approx(1.8)
    assert sides["largest_share"] == pytest.approx(0.6 / 1.8)
    assert sides["efficiency"] == pytest.approx(4.5 / (3 * 2))
    assert figures["tracing"]["largest_share"] == pytest.approx(0.75)
    everything = whole(timeline, process_wall_s=8.5)
    assert everything["startup_s"] == pytest.approx(1.5)
    assert everything["cpu_s"] == pytest.approx(10.5)
    assert everything["serial_s"] == pytest.approx(1.75)
    assert everything["efficiency"] == pytest.approx(10.5 / (7 * 2))


def test_tracing_stalls_are_the_gaps_between_chunks_named_by_what_ran_longest():
    """Within the tracing stage (its visits with chunks), the intervals of 10 ms or more
    that no chunk covers, on any thread, each put down to the kind of item that ran
    longest in it (waits left out; "nothing" where none ran); shorter gaps, gaps outside
    the stage and a tracing visit without chunks count nothing."""
    chunks = [(1, 1, "trace", 0.0, 1.0), (1, 2, "trace", 0.2, 0.9),  # covered to 1.0
              (1, 1, "trace", 1.005, 2.0),  # a 5 ms gap: not a stall
              (2, 1, "trace", 2.5, 3.0), (2, 2, "trace", 3.6, 3.9)]
    beside = [(3, 3, "commit", 1.9, 2.4), (3, 4, "commit", 1.9, 2.4),  # 0.8 s in 2.0-2.5
              (4, 3, "surface", 2.45, 2.5), (5, 1, "wait", 2.0, 2.5),
              (6, 3, "layout", 3.0, 3.2), (6, 3, "bvh", 3.2, 3.5)]  # 3.0-3.6: 0.3 s bvh
    timeline = _timeline([
        _stage("seen sides", -1, 1, [(0, 1, "side probes", -1.0, 0.0)]),
        _stage("tracing", 0, 4, chunks + beside),  # 3.9-4.0: nothing ran
        _stage("tracing", 4, 1, [(7, 1, "shadow rays", 4.0, 5.0)]),
    ], threads=4)
    stalls = tracing_stalls(timeline)
    assert stalls["tracing_s"] == pytest.approx(4)
    assert stalls["stalled_s"] == pytest.approx(0.5 + 0.6 + 0.1)
    assert stalls["by"] == pytest.approx({"commit": 0.5, "bvh": 0.6, "nothing": 0.1})


def test_counters_add_up_stages_by_name_and_name_the_most_kernel_time():
    """A run's OS counters added up per stage name (`aggregate`) and whole (`whole`); its
    line gives the kernel's share of the CPU, the faults and switches in thousands and
    the stages of the most kernel time; a timeline recorded without counters has none."""
    counts = {"tracing": (8.0, 1.5, 700_000, 1, 9_000, 3_000),
              "seen sides": (3.0, 0.25, 50_000, 0, 2_500, 100), "load": (0.5, 0.0, 12, 0, 3, 1)}
    stages = []
    for name, values in [("load", counts["load"]), ("seen sides", counts["seen sides"]),
                         ("tracing", counts["tracing"]), ("tracing", counts["tracing"])]:
        stage = _stage(name, 0, 1, [])
        stage.update(zip(COUNTERS, values, strict=True))
        stages.append(stage)
    timeline = _timeline(stages)
    by_stage, everything = aggregate(timeline), whole(timeline, 9.0)
    assert list(by_stage) == ["load", "seen sides", "tracing"]
    assert by_stage["tracing"]["minor_faults"] == 1_400_000
    assert everything["system_s"] == pytest.approx(3.25)
    assert everything["user_s"] == pytest.approx(19.5)
    assert counters_line("bake", "2 threads", by_stage, everything) == (
        "bake kernel, 2 threads: 3.25 s of its 22.75 s CPU in the kernel (14.3%), 1450.0 k "
        "page faults (2 from disk), 20.5 k waits and 6.1 k preemptions; most kernel time: "
        "tracing 3.00 s (1400.0 k faults), seen sides 0.25 s (50.0 k faults)")
    bare = _timeline([_stage("load", 0, 1, [])])
    assert not set(COUNTERS) & (set(aggregate(bare)["load"]) | set(whole(bare, 1.0)))


def test_predictions_take_the_serial_seconds_of_the_most_threads():
    one = _timeline([_stage("tracing", 0, 10, _batch(1, "trace", 0, [2.5] * 4), serial=10)])
    two = _timeline([_stage("tracing", 0, 6, _batch(1, "trace", 0, [2.5, 2.5])
                            + _batch(1, "trace", 0, [2.5, 2.5], tid=2), serial=1)], threads=2)
    p = predictions(one, two)
    assert p["tracing"]["serial_s"] == pytest.approx(1)
    assert p["tracing"]["amdahl"]["16"] == pytest.approx(10 / (1 + 9 / 16))
    assert p["tracing"]["replay"]["64"] == pytest.approx(4)  # four items of 2.5 s
    assert p["whole"]["replay"]["2"] == pytest.approx(2)


def test_thread_counts_and_labels():
    assert default_threads(1) == [1]
    assert default_threads(2) == [1, 2]
    assert default_threads(6) == [1, 2, 4, 6]
    assert default_threads(8) == [1, 2, 4, 8]
    assert thread_counts("4,2", 8) == [1, 2, 4]
    assert thread_counts(None, 3) == [1, 2, 3]
    for bad in ("0", "two", ""):
        with pytest.raises(CLIError):
            thread_counts(bad, 4)
    stages = [_stage("levels", 0, 0.01, []), _stage("paths onto levels", 0.011, 5, []),
              _stage("tracing", 5.011, 4, []), _stage("tracing", 9.011, 1, [])]
    assert stage_labels(stages, 0.1) == [(0.011, "paths onto levels"), (5.011, "tracing")]


def test_a_run_deletes_the_outputs_first_and_reads_the_timeline(tmp_path):
    (tmp_path / "bake.npz").write_text("an earlier bake")
    code = ("import json, pathlib, sys; w = pathlib.Path(sys.argv[1]); "
            "assert not (w / 'bake.npz').exists(); "
            "(w / 'timeline.json').write_text(json.dumps({'wall_s': 1.5}))")
    wall, timeline = run_child([sys.executable, "-c", code, str(tmp_path)], tmp_path)
    assert timeline == {"wall_s": 1.5} and wall > 0
    with pytest.raises(CLIError, match="failed"):
        run_child([sys.executable, "-c", "raise SystemExit(3)"], tmp_path)
    assert median_run([(3.0, "c"), (1.0, "a"), (2.0, "b")]) == (2.0, "b")
    assert median_run([(2.0, "b"), (1.0, "a")]) == (1.0, "a")


def test_the_sameness_line_names_the_runs_that_differ():
    runs = [{"threads": 1, "scheduler": None, "digests": ["aa" * 32, "aa" * 32]},
            {"threads": 4, "scheduler": None, "digests": ["bb" * 32]},
            {"threads": 4, "scheduler": "local:4", "digests": ["aa" * 32]}]
    line = sameness_line("bake", runs)
    assert line.startswith("bake: a DIFFERENT lattice (decoded arrays) between runs: ")
    assert "aaaaaaaaaaaa: 1 thread #1, 1 thread #2, dask local:4 #1" in line
    assert "bbbbbbbbbbbb: 4 threads #1" in line
    assert sameness_line("render", runs[:1]) == ("render: the same picture (pixels) from "
                                                 "every run (2)")


def test_bench_cores_measures_the_commands_defaults_with_samples_0(tmp_path, capsys):
    """``--samples N`` is passed to every command; 0 passes none, so that the bake runs to
    its texel error as a user's does; a negative count is refused."""
    from argparse import Namespace

    args = Namespace(volume="v.raw", samples=16, size="64x64")
    bake = command_argv(args, "bake", 2, tmp_path)
    assert bake[bake.index("--samples") + 1] == "16"
    args.samples = 0
    for command in ("bake", "render"):
        words = command_argv(args, command, 2, tmp_path)
        assert "--samples" not in words and words[words.index("--workers") + 1] == "2"
    assert main(["bench", "cores", "--samples", "-1", "--out", str(tmp_path / "c")]) != 0
    assert "--samples -1: expected 0" in capsys.readouterr().err


def test_bench_cores_end_to_end(tmp_path, capsys):
    out = tmp_path / "cores"
    assert main(["bench", "cores", "synthetic:engine:64", "--samples", "2", "--threads",
                 "1,2", "--repeats", "1", "--commands", "bake", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    record = json.loads((out / "cores.json").read_text())
    assert {"settings", "available_cores", "load_average_before", "load_average_after",
            "results"} <= set(record)
    assert list(record["results"]) == ["bake"]
    bake = record["results"]["bake"]
    runs = {r["label"]: r for r in bake["runs"]}
    assert set(runs) == {"1", "2"}
    for label, r in runs.items():
        words = r["timeline"]["command"]
        assert words[words.index("--workers") + 1] == label
        assert r["timeline"]["threads"] == int(label)
        assert len(r["process_walls_s"]) == 1
        assert r["whole"]["process_wall_s"] > r["whole"]["wall_s"] > 0
        assert {"paths onto levels", "tracing"} <= set(r["stages"])
        assert r["stages"]["tracing"]["items"] > 0
        assert len(r["digests"]) == 1
    assert runs["1"]["digests"] == runs["2"]["digests"]
    assert "bake: the same lattice (decoded arrays) from every run (2)" in printed
    predicted = bake["predicted"]
    assert {"paths onto levels", "tracing", "whole"} <= set(predicted)
    # on one simulated thread the replay is the one-thread run itself
    assert 0.9 <= predicted["whole"]["replay"]["1"] <= 1.0 + 1e-9
    assert predicted["whole"]["replay"]["64"] >= predicted["whole"]["replay"]["16"] >= 1.0
    assert 1.0 <= predicted["whole"]["amdahl"]["64"] <= 64
    for name in ("gantt.png", "speedup.png"):
        path = out / name
        assert path.stat().st_size > 20_000
        with Image.open(path) as image:
            assert image.width >= 600 and image.height >= 400
            assert len(image.convert("L").getcolors(1 << 16)) > 20  # not blank
    table = printed[printed.index("stage "):]
    assert "tracing" in table and "paths onto levels" in table
    assert "bake whole, 2 threads" in printed and str(out / "cores.json") in printed
    stalls = runs["2"]["stalls"]
    assert 0 <= stalls["stalled_s"] <= stalls["tracing_s"] == pytest.approx(
        runs["2"]["stages"]["tracing"]["wall_s"])
    assert sum(stalls["by"].values()) == pytest.approx(stalls["stalled_s"])
    assert f"bake tracing, 2 threads: no chunk tracing for {stalls['stalled_s']:.2f} s" \
        in printed
    for r in runs.values():
        whole_counts = r["whole"]
        assert whole_counts["minor_faults"] > 0 and whole_counts["user_s"] > 0
        assert all(set(COUNTERS) <= set(f) for f in r["stages"].values())
        assert f"bake kernel, {run_name(r)}: {whole_counts['system_s']:.2f} s of its" in printed
