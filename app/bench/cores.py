"""``isolume bench cores``: where a bake's and a render's cores go, stage by stage, and how
far more threads would take them.

Each command (``bake``, ``render``) runs once untimed (the compiled kernels cached; not
with ``--no-warmup``), then
``--repeats`` times per thread count, each run in a fresh child process with
``--workers N --timeline FILE.json`` (`isolume.volumes.cores.Timeline`); the run of median
wall time (the whole process, interpreter start included) is kept. Per stage (its visits
added up by name) and for the whole command: wall and CPU seconds, the parallel
efficiency (CPU / (wall × threads)), the serial seconds (sampled intervals with at most
one core busy), the largest work item's share of the stage's items; how long the
tracing had no chunk running, by what ran instead (`tracing_stalls`); and the kernel
time, page faults and context switches the OS counted (`counters_line`).

Two predictions for 16 and 64 threads, both from the one-thread run:

* Amdahl: T1 / (S + (T1 − S) / N), S the serial seconds of the run with the most threads;
* replay: the one-thread run played again on N simulated threads (`app.bench.replay`).

Every run's output is compared (`output_digest`: a bake's decoded lattice arrays, a
render's pixels) and a line says whether all thread counts (and Dask) wrote the same.

Writes ``cores.json`` (every run's figures, timeline and digests, the predictions) and the charts
``gantt.png`` (the run with the most threads: items per thread coloured by stage, the
cores busy) and ``speedup.png`` (measured, Amdahl, replay, ideal) into ``--out``.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from isolume.app.bench.counters import COUNTERS, counters_line
from isolume.app.bench.replay import (
    duration,
    inner_factors,
    outside_stages_s,
    replay,
    split_hints,
)
from isolume.app.bench.stalls import stall_line, tracing_stalls
from isolume.app.render.images import output_folder
from isolume.volumes import cores

HELP = ("parallel efficiency of bake and render per stage against threads, and their "
        "speed-up predicted at 16 and 64 threads")
COMMANDS = ("bake", "render")
PREDICT_AT = (16, 64)
"""Thread counts the predictions are printed for."""
CURVE_AT = (1, 2, 4, 8, 16, 32, 64)
"""Thread counts the replay curve of ``speedup.png`` is computed at."""
BUSY_LOAD = 0.5
"""A 1-minute load average above this before the runs: other processes use the cores
(a note is printed)."""
TIMEOUT_S = 3600.0
"""Longest a measured child process may run."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("volume", nargs="?", default="synthetic:engine",
                   help="volume (default synthetic:engine)")
    p.add_argument("--samples", type=int, default=16,
                   help="paths per texel of the bake and of the render's traced global "
                   "illumination (default 16; 0: each command's own default, the bake's "
                   "to its texel error)")
    p.add_argument("--threads", default=None, metavar="N,N,...",
                   help="thread counts (default 1, 2, 4, ... up to the cores this process "
                   "may use, that count included); 1 always runs: the predictions start "
                   "from it")
    p.add_argument("--repeats", type=int, default=3,
                   help="runs per command and thread count, the median kept (default 3)")
    p.add_argument("--commands", default=",".join(COMMANDS), metavar="bake,render",
                   help="commands to measure (default bake,render)")
    p.add_argument("--size", default="512x512", metavar="WxH",
                   help="render picture size (default 512x512)")
    p.add_argument("--out", default="bench-cores", metavar="DIR",
                   help="folder for cores.json, gantt.png and speedup.png "
                   "(default bench-cores)")
    p.add_argument("--warmup", action=argparse.BooleanOptionalAction, default=True,
                   help="one untimed run of each command first, so that the compiled "
                   "kernels are cached (default on; --no-warmup where an earlier run of "
                   "the same volume cached them)")
    p.add_argument("--dask", action="store_true",
                   help="also bake with --scheduler local:N at the most threads "
                   "(needs isolume[cluster])")


# -- options ------------------------------------------------------------------------------
def default_threads(available: int) -> list[int]:
    """1, 2, 4, … below `available`, and `available` itself."""
    counts = [1]
    while counts[-1] * 2 < available:
        counts.append(counts[-1] * 2)
    return sorted({*counts, available})


def thread_counts(text: str | None, available: int) -> list[int]:
    """The thread counts of ``--threads`` (None: `default_threads`), sorted, 1 included.
    Raises CLIError on a word that is not a positive integer."""
    from isolume.app.options import CLIError

    if text is None:
        return default_threads(available)
    try:
        counts = {int(word) for word in text.split(",") if word.strip()}
    except ValueError:
        raise CLIError(f"--threads {text}: expected positive integers, e.g. 1,2,4") from None
    if not counts or min(counts) < 1:
        raise CLIError(f"--threads {text}: expected positive integers, e.g. 1,2,4")
    return sorted(counts | {1})


def command_list(text: str) -> list[str]:
    """The commands of ``--commands`` in `COMMANDS` order. Raises CLIError on others."""
    from isolume.app.options import CLIError

    words = {word.strip() for word in text.split(",") if word.strip()}
    if not words or not words <= set(COMMANDS):
        raise CLIError(f"--commands {text}: expected bake, render or bake,render")
    return [c for c in COMMANDS if c in words]


# -- the runs -----------------------------------------------------------------------------
def _cli(*words: str) -> list[str]:
    """The argv of ``isolume WORDS`` in this interpreter."""
    return [sys.executable, "-c", "import sys; from isolume.app.cli import main; "
            "sys.exit(main())", *words]


def command_argv(args: argparse.Namespace, command: str, threads: int, work: Path,
                 scheduler: str | None = None) -> list[str]:
    """The command line of `command` on ``args.volume`` with `threads` workers, writing its
    output and its timeline (``timeline.json``) into `work`."""
    samples = ["--samples", str(args.samples)] if args.samples > 0 else []
    words = [command, args.volume, *samples, "--workers", str(threads),
             "--timeline", str(work / "timeline.json")]
    if command == "bake":
        words += ["--out", str(work / "bake.npz")]
    else:
        words += ["--size", args.size, "--out", str(work / "render.png")]
    if scheduler:
        words += ["--scheduler", scheduler]
    return _cli(*words)


def run_child(argv: list[str], work: Path) -> tuple[float, dict[str, Any]]:
    """Run `argv` (a fresh process) after deleting its outputs in `work` (a bake resumes
    from an existing file); (its wall seconds, its timeline). Raises CLIError when it
    fails."""
    from isolume.app.options import CLIError

    for name in ("bake.npz", "render.png", "timeline.json"):
        (work / name).unlink(missing_ok=True)
    with tempfile.TemporaryFile() as log:
        began = time.perf_counter()
        child = subprocess.run(argv, stdout=log, stderr=subprocess.STDOUT,
                               timeout=TIMEOUT_S, check=False)
        wall = time.perf_counter() - began
        log.seek(0)
        text = log.read().decode(errors="replace")
    if child.returncode != 0 or not (work / "timeline.json").exists():
        tail = " | ".join(text.strip().splitlines()[-5:])
        raise CLIError(f"bench cores: {' '.join(argv[3:])} failed "
                       f"(exit {child.returncode}): {tail}")
    return wall, json.loads((work / "timeline.json").read_text())


LATTICE_ARRAYS = ("active", "facing", "samples", "second", "values")
"""The decoded arrays a bake's output is compared by (dense over its box)."""


def output_digest(command: str, work: Path) -> str:
    """SHA-256 of what `command` wrote into `work`: a bake's lattice as its decoded
    `LATTICE_ARRAYS` (not the file's bytes, which hold timings), a render's picture as its
    pixels. Equal digests: the same lattice or picture to the bit."""
    from PIL import Image

    from isolume.baking.lattice import Lattice

    if command == "bake":
        lattice = Lattice.load(work / "bake.npz")
        arrays = [getattr(lattice, name) for name in LATTICE_ARRAYS]
    else:
        with Image.open(work / "render.png") as picture:
            arrays = [np.asarray(picture)]
    digest = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def median_run(runs: list[tuple[float, dict[str, Any]]]) -> tuple[float, dict[str, Any]]:
    """The run of median wall time (the lower one of an even count)."""
    ordered = sorted(runs, key=lambda run: run[0])
    return ordered[(len(ordered) - 1) // 2]


# -- the figures (pure) -------------------------------------------------------------------
def efficiency(cpu_s: float, wall_s: float, threads: int) -> float | None:
    """CPU seconds over the seconds `threads` cores had (1: all busy); None for no wall."""
    return cpu_s / (wall_s * threads) if wall_s > 0 else None


def aggregate(timeline: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per stage name, in the order first visited: its visits added up — visits, wall_s,
    cpu_s, serial_s, items, item_s (seconds of its items), largest_item_s, and the OS's
    `COUNTERS` where the timeline has them — and efficiency, largest_share (largest item
    over item_s; None without items)."""
    out: dict[str, dict] = {}
    for stage in timeline["stages"]:
        f = out.setdefault(stage["name"], {"visits": 0, "wall_s": 0.0, "cpu_s": 0.0,
                                           "serial_s": 0.0, "items": 0, "item_s": 0.0,
                                           "largest_item_s": 0.0})
        seconds = [duration(item) for item in stage["items"] if item[2] != "wait"]
        f["visits"] += 1
        f["wall_s"] += stage["wall_s"]
        f["cpu_s"] += stage["cpu_s"]
        f["serial_s"] += stage.get("serial_s", 0.0)
        f["items"] += len(seconds)
        f["item_s"] += sum(seconds)
        f["largest_item_s"] = max([f["largest_item_s"], *seconds])
        for counter in COUNTERS:
            if counter in stage:
                f[counter] = f.get(counter, 0) + stage[counter]
    for f in out.values():
        f["efficiency"] = efficiency(f["cpu_s"], f["wall_s"], timeline["threads"])
        f["largest_share"] = f["largest_item_s"] / f["item_s"] if f["item_s"] > 0 else None
    return out


def whole(timeline: dict[str, Any], process_wall_s: float) -> dict[str, Any]:
    """The whole command's figures: wall_s (the timeline's), process_wall_s (with the
    interpreter's start and imports), startup_s (their difference), cpu_s, serial_s (the
    stages' and the time outside them), efficiency, others_cpu_s and stolen_s (the CPU
    seconds other processes used on its cores, and the hypervisor took from them, during
    its stages), and the OS's `COUNTERS` summed where every stage has them."""
    counted = {c: sum(s[c] for s in timeline["stages"]) for c in COUNTERS
               if timeline["stages"] and all(c in s for s in timeline["stages"])}
    cpu = sum(s["cpu_s"] for s in timeline["stages"])
    serial = sum(s.get("serial_s", 0.0) for s in timeline["stages"])
    wall = timeline["wall_s"]
    return {"wall_s": wall, "process_wall_s": process_wall_s,
            "startup_s": process_wall_s - wall, "cpu_s": cpu,
            "serial_s": serial + outside_stages_s(timeline),
            "efficiency": efficiency(cpu, wall, timeline["threads"]),
            "others_cpu_s": _known_sum(s.get("others_cpu_s") for s in timeline["stages"]),
            "stolen_s": _known_sum(s.get("stolen_s") for s in timeline["stages"]),
            **counted}


def _known_sum(values: Iterable[float | None]) -> float | None:
    """The sum of `values`, None if any is None (a figure the timeline could not tell)."""
    values = list(values)
    return None if any(v is None for v in values) else float(sum(values))


def amdahl(t1: float, serial: float, n: float) -> float:
    """Amdahl's speed-up on `n` threads: t1 / (S + (t1 − S) / n), S clamped to [0, t1]."""
    if t1 <= 0:
        return 1.0
    serial = min(max(serial, 0.0), t1)
    return t1 / (serial + (t1 - serial) / n)


def predictions(one: dict[str, Any], most: dict[str, Any]) -> dict[str, Any]:
    """Speed-ups at `PREDICT_AT` and `CURVE_AT` threads of each stage and the whole command,
    from the one-thread timeline `one` and the timeline `most` with the most threads (its
    serial seconds for Amdahl, its cut of parallel calls for the replay)."""
    stages1, stages_n = aggregate(one), aggregate(most)
    hints = split_hints(most) if most["threads"] > 1 else {}
    inner = inner_factors(one, most)
    t1 = {name: f["wall_s"] for name, f in stages1.items()}
    t1["whole"] = one["wall_s"]
    serial = {name: stages_n.get(name, {}).get("serial_s", 0.0) for name in stages1}
    serial["whole"] = whole(most, most["wall_s"])["serial_s"]
    counts = sorted({*CURVE_AT, *PREDICT_AT})
    replays = {n: replay(one, n, hints, inner) for n in counts}
    out = {}
    for name in t1:
        out[name] = {
            "t1_s": t1[name], "serial_s": serial[name],
            "amdahl": {str(n): amdahl(t1[name], serial[name], n) for n in counts},
            "replay_s": {str(n): replays[n][name] for n in counts},
            "replay": {str(n): t1[name] / replays[n][name] if replays[n][name] > 0 else 1.0
                       for n in counts},
        }
    return out


def measured_speedups(runs: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per run label: the one-thread run's wall over its, per stage, for the whole
    timeline ("whole") and the whole process ("process")."""
    one = next(r for r in runs if r["threads"] == 1 and r["scheduler"] is None)
    out = {}
    for r in runs:
        ratios = {name: one["stages"][name]["wall_s"] / f["wall_s"]
                  for name, f in r["stages"].items() if name in one["stages"] and f["wall_s"]}
        ratios["whole"] = one["whole"]["wall_s"] / r["whole"]["wall_s"]
        ratios["process"] = one["whole"]["process_wall_s"] / r["whole"]["process_wall_s"]
        out[r["label"]] = ratios
    return out


def figures_of(command: str, label: str, threads: int, scheduler: str | None,
               walls: list[float], kept: tuple[float, dict[str, Any]]) -> dict[str, Any]:
    """A run's record for cores.json: its settings, every repeat's wall, the kept run's
    per-stage and whole figures and its timeline."""
    wall, timeline = kept
    return {"command": command, "label": label, "threads": threads, "scheduler": scheduler,
            "process_walls_s": walls, "stages": aggregate(timeline),
            "whole": whole(timeline, wall), "stalls": tracing_stalls(timeline),
            "timeline": timeline}


# -- printing -----------------------------------------------------------------------------
def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.0%}"


def run_name(run: dict) -> str:
    if run["scheduler"]:
        return f"dask {run['scheduler']}"
    return f"{run['threads']} thread" + ("s" if run["threads"] > 1 else "")


def table(command: str, runs: list[dict[str, Any]], predicted: dict[str, Any]) -> list[str]:
    """The lines of one command's table: per stage, each run's wall, CPU and efficiency,
    then the serial seconds and largest item share of the run with the most threads and
    the replay's predicted speed-ups; then the whole command."""
    most = max((r for r in runs if r["scheduler"] is None), key=lambda r: r["threads"])
    cell = "{:>7} {:>7} {:>5}"
    head = f"{command:<18}" + "".join(f" | {run_name(r):^21}" for r in runs)
    head += f" | {'serial':>7} {'largest':>7} | {'replay speed-up':>15}"
    sub = f"{'stage':<18}" + "".join(" | " + cell.format("wall s", "cpu s", "eff")
                                     for _ in runs)
    sub += f" | {'s':>7} {'item':>7} | " + " ".join(f"{f'x{n}':>7}" for n in PREDICT_AT)
    lines = [head, sub]
    names = dict.fromkeys(name for r in runs for name in r["stages"])
    for name in names:
        row = f"{name:<18}"
        for r in runs:
            f = r["stages"].get(name)
            row += " | " + (cell.format(f"{f['wall_s']:.2f}", f"{f['cpu_s']:.2f}",
                                        _pct(f["efficiency"])) if f else cell.format(*"---"))
        f = most["stages"].get(name, {})
        row += f" | {f.get('serial_s', 0.0):>7.2f} {_pct(f.get('largest_share')):>7} | "
        row += " ".join(f"{predicted[name]['replay'][str(n)]:>7.1f}" if name in predicted
                        else f"{'-':>7}" for n in PREDICT_AT)
        lines.append(row)
    return lines


def _seconds(value: float | None) -> str:
    """``1.2 s``, or ``n/a`` for a figure the timeline could not tell."""
    return "n/a" if value is None else f"{value:.1f} s"


def whole_lines(command: str, runs: list[dict[str, Any]], predicted: dict[str, Any]) -> list[str]:
    """The whole command: each run's process and timeline wall, CPU, efficiency, measured
    speed-up, peak memory, the CPU other processes used on its cores and the time stolen
    from them; where a run of several threads traced, how long no chunk traced and what
    ran meanwhile (`tracing_stalls`); what the OS counted (`counters_line`); Amdahl's and
    the replay's predictions."""
    speedups = measured_speedups(runs)
    lines = []
    for r in runs:
        w = r["whole"]
        lines.append(f"{command} whole, {run_name(r)}: process {w['process_wall_s']:.2f} s "
                     f"(start-up {w['startup_s']:.2f} s), timeline {w['wall_s']:.2f} s, "
                     f"cpu {w['cpu_s']:.2f} s, efficiency {_pct(w['efficiency'])}, serial "
                     f"{w['serial_s']:.2f} s; speed-up x{speedups[r['label']]['whole']:.2f} "
                     f"(process x{speedups[r['label']]['process']:.2f}); peak memory "
                     f"{r['timeline'].get('peak_rss_mb', 0):.0f} MiB; other processes "
                     f"{_seconds(w.get('others_cpu_s'))} CPU on its cores, stolen "
                     f"{_seconds(w.get('stolen_s'))}")
    lines += [stall_line(command, run_name(r), r["stalls"]) for r in runs
              if r["threads"] > 1 and r["stalls"]["tracing_s"] > 0]
    lines += [counters_line(command, run_name(r), r["stages"], r["whole"]) for r in runs
              if "system_s" in r["whole"]]
    p = predicted["whole"]
    lines.append(f"{command} whole, predicted from 1 thread (T1 {p['t1_s']:.2f} s, serial "
                 f"{p['serial_s']:.2f} s): " + ", ".join(
                     f"{n} threads: Amdahl x{p['amdahl'][str(n)]:.1f}, replay "
                     f"x{p['replay'][str(n)]:.1f}" for n in PREDICT_AT))
    return lines


def sameness_line(command: str, runs: list[dict[str, Any]]) -> str:
    """Whether every run of `command` wrote the same output (`output_digest`), or which
    runs wrote which."""
    what = "lattice (decoded arrays)" if command == "bake" else "picture (pixels)"
    groups: dict[str, list[str]] = {}
    for r in runs:
        for i, digest in enumerate(r.get("digests", [])):
            groups.setdefault(digest, []).append(f"{run_name(r)} #{i + 1}")
    if len(groups) <= 1:
        return f"{command}: the same {what} from every run ({sum(map(len, groups.values()))})"
    parts = "; ".join(f"{digest[:12]}: {', '.join(names)}" for digest, names in groups.items())
    return f"{command}: a DIFFERENT {what} between runs: {parts}"


def inner_line(inner: dict[str, float], threads: int) -> str:
    """How the replay took the items parallel inside (`inner_factors`)."""
    if threads <= 1:
        return "replay: items parallel inside (" + ", ".join(inner) + ") taken as serial"
    fitted = ", ".join(f"{kind} serial fraction {f:.2f} (x{threads / (f * threads + 1 - f):.2f} "
                       "measured)" for kind, f in inner.items())
    return f"replay: items parallel inside, Amdahl fitted to 1 against {threads} threads: {fitted}"


# -- charts -------------------------------------------------------------------------------
ROW_IN = 0.3
"""Height of a thread's row in ``gantt.png``, inches."""
LABEL_IN = 1.0
"""Height above the rows kept for the stages' names, inches."""


def _stage_colour(name: str):
    import matplotlib

    index = cores.STAGES.index(name) if name in cores.STAGES else len(cores.STAGES)
    return matplotlib.colormaps["tab20"](index % 20)


def _thread_rows(timeline: dict) -> list[int]:
    """The thread ids with items, the main thread first, then by name."""
    names = timeline.get("thread_names", {})
    tids = {item[1] for stage in timeline["stages"] for item in stage["items"]}
    return sorted(tids, key=lambda t: (names.get(str(t)) != "MainThread",
                                       names.get(str(t), ""), t))


def stage_labels(stages: list[dict[str, Any]], gap_s: float) -> list[tuple[float, str]]:
    """(start seconds, name) of the stage visits to name on a chart: the longest first,
    each name once, none within `gap_s` of another."""
    chosen: list[tuple[float, str]] = []
    for stage in sorted(stages, key=lambda s: -s["wall_s"]):
        x = stage["start_s"]
        if stage["name"] not in {n for _, n in chosen} and all(
                abs(x - other) > gap_s for other, _ in chosen):
            chosen.append((x, stage["name"]))
    return sorted(chosen)


def _gantt_panel(ax, strip, run: dict) -> None:
    """One run's items per thread coloured by stage (`ax`) and its busy cores (`strip`)."""
    timeline = run["timeline"]
    rows = _thread_rows(timeline)
    names = timeline.get("thread_names", {})
    for stage in timeline["stages"]:
        colour = _stage_colour(stage["name"])
        for y, tid in enumerate(rows):
            bars = [(item[3], duration(item)) for item in stage["items"] if item[1] == tid]
            if bars:
                ax.broken_barh(bars, (y - 0.4, 0.8), facecolors=colour, linewidth=0)
        strip.axvspan(stage["start_s"], stage["end_s"], color=colour, alpha=0.35, lw=0)
        for axis in (ax, strip):
            axis.axvline(stage["start_s"], color="0.3", lw=0.6)
    for x, name in stage_labels(timeline["stages"], 0.012 * timeline["wall_s"]):
        ax.text(x, 0.985, " " + name, rotation=90, va="top", ha="left", fontsize=7,
                transform=ax.get_xaxis_transform())
    ax.set_yticks(range(len(rows)), [f"{names.get(str(t), t)}" for t in rows], fontsize=7)
    ax.set_ylim(-0.6, len(rows) - 0.4 + LABEL_IN / ROW_IN)
    ax.set_title(f"{run['command']}, {run_name(run)}: work items per thread", fontsize=9,
                 loc="left")
    busy = timeline.get("busy", [])
    if busy:
        ts = [timeline["busy"][0][0] - timeline.get("sample_s", 0.05)] + [t for t, _ in busy]
        strip.stairs([c for _, c in busy], ts, color="k", lw=0.8)
    strip.axhline(timeline["threads"], color="C3", ls="--", lw=0.8)
    strip.set_ylim(0, max([timeline["threads"], *(c for _, c in busy)]) * 1.15)
    strip.set_ylabel("cores\nbusy", fontsize=7)
    strip.set_xlabel("seconds since the timeline began", fontsize=8)
    strip.set_xlim(0, timeline["wall_s"])


def gantt_chart(runs: list[dict[str, Any]], path: Path) -> None:
    """``gantt.png``: per command, its run with the most threads."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    shown = [max((r for r in runs if r["command"] == c and r["scheduler"] is None),
                 key=lambda r: r["threads"]) for c in dict.fromkeys(r["command"] for r in runs)]
    heights = []
    for r in shown:
        heights += [LABEL_IN + 0.3 + ROW_IN * len(_thread_rows(r["timeline"])), 0.9]
    fig, axes = plt.subplots(len(heights), 1, figsize=(12, sum(heights) + 0.8),
                             gridspec_kw={"height_ratios": heights})
    used: dict[str, None] = {}
    for k, r in enumerate(shown):
        ax, strip = axes[2 * k], axes[2 * k + 1]
        strip.sharex(ax)
        _gantt_panel(ax, strip, r)
        used.update(dict.fromkeys(s["name"] for s in r["timeline"]["stages"]))
    fig.legend(handles=[Patch(color=_stage_colour(n), label=n) for n in used],
               loc="upper center", ncol=min(8, len(used)), fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / (sum(heights) + 0.8)))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def speedup_chart(results: dict[str, Any], path: Path) -> None:
    """``speedup.png``: per command, the whole command's speed-up against threads."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    commands = list(results)
    fig, axes = plt.subplots(1, len(commands), figsize=(5.6 * len(commands), 4.4),
                             squeeze=False)
    for ax, command in zip(axes[0], commands, strict=True):
        runs, p = results[command]["runs"], results[command]["predicted"]["whole"]
        speedups = measured_speedups(runs)
        n = np.geomspace(1, 64, 200)
        ax.plot(n, n, color="0.6", ls=":", label="ideal")
        ax.plot(n, [amdahl(p["t1_s"], p["serial_s"], x) for x in n], color="C0",
                label=f"Amdahl (serial {p['serial_s']:.2f} s of {p['t1_s']:.2f} s)")
        counts = sorted(int(k) for k in p["replay"])
        ax.plot(counts, [p["replay"][str(c)] for c in counts], "o-", color="C1", ms=3,
                label="replay of the 1-thread items")
        plain = [r for r in runs if r["scheduler"] is None]
        ax.plot([r["threads"] for r in plain], [speedups[r["label"]]["whole"] for r in plain],
                "s", color="C3", ms=7, label="measured (timeline)")
        ax.plot([r["threads"] for r in plain], [speedups[r["label"]]["process"] for r in plain],
                "x", color="k", ms=7, label="measured (whole process)")
        for r in runs:
            if r["scheduler"]:
                ax.plot(r["threads"], speedups[r["label"]]["whole"], "D", color="C2", ms=7,
                        label=f"dask {r['scheduler']}")
        for c in PREDICT_AT:  # the higher prediction's figure above, the lower's below
            pair = sorted(((p["replay"][str(c)], "C1"), (p["amdahl"][str(c)], "C0")))
            last = c == max(PREDICT_AT)  # written to the left of the point, inside the axes
            for (value, colour), dy in zip(pair, (-11, 5), strict=True):
                ax.annotate(f"{value:.1f}", (c, value), textcoords="offset points",
                            xytext=(-5 if last else 5, dy), fontsize=7, color=colour,
                            ha="right" if last else "left")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log", base=2)
        ax.set_xlim(0.9, 72)
        lowest = min(0.8, *(0.8 * s["whole"] for s in speedups.values()))
        ax.set_ylim(lowest, 72)
        ticks = [1, 2, 4, 8, 16, 32, 64]
        ax.set_xticks(ticks, [str(t) for t in ticks])
        ax.set_yticks([t for t in (0.25, 0.5) if t > lowest] + ticks,
                      [str(t) for t in (0.25, 0.5) if t > lowest] + [str(t) for t in ticks])
        ax.set_xlabel("threads")
        ax.set_ylabel("speed-up over 1 thread")
        ax.set_title(f"{command}", fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- the benchmark ------------------------------------------------------------------------
def measure_command(args: argparse.Namespace, command: str, counts: list[int], work: Path,
                    dask: str | None) -> list[dict[str, Any]]:
    """One command: a warm-up (unless not `args.warmup`), then `args.repeats` rounds over
    the thread counts (and the Dask scheduler `dask`, a bake only), a line printed per
    run; each count's median run."""
    plans = [(str(n), n, None) for n in counts]
    if dask and command == "bake":
        plans.append((dask, max(counts), dask))
    if args.warmup:
        run_child(command_argv(args, command, max(counts), work), work)  # kernels cached
    walls: dict[str, list[tuple[float, dict]]] = {label: [] for label, _, _ in plans}
    digests: dict[str, list[str]] = {label: [] for label, _, _ in plans}
    for repeat in range(args.repeats):
        for label, n, scheduler in plans:
            wall, timeline = run_child(command_argv(args, command, n, work, scheduler), work)
            walls[label].append((wall, timeline))
            digests[label].append(output_digest(command, work))
            name = run_name({"threads": n, "scheduler": scheduler})
            print(f"  {command}, {name}, run {repeat + 1}/{args.repeats}: {wall:.2f} s",
                  flush=True)
    return [{**figures_of(command, label, n, scheduler, [w for w, _ in walls[label]],
                          median_run(walls[label])), "digests": digests[label]}
            for label, n, scheduler in plans]


def _load() -> float:
    return os.getloadavg()[0]


def run(args: argparse.Namespace) -> int:
    """Measure, predict, print the tables, write cores.json and the charts."""
    from isolume.app.options import CLIError

    commands = command_list(args.commands)
    counts = thread_counts(args.threads, cores.available())
    if args.repeats < 1:
        raise CLIError(f"--repeats {args.repeats}: expected at least 1")
    if args.samples < 0:
        raise CLIError(f"--samples {args.samples}: expected 0 (the commands' defaults) "
                       "or more paths per texel")
    if not re.fullmatch(r"\d+x\d+", args.size):
        raise CLIError(f"--size {args.size}: expected WxH, e.g. 512x512")
    dask = None
    if args.dask:
        if importlib.util.find_spec("distributed") is None:
            print("--dask: dask.distributed is not installed (pip install 'isolume[cluster]'); "
                  "skipped")
        else:
            dask = f"local:{max(counts)}"
    out = output_folder(args.out)
    before = os.getloadavg()
    paths = f"{args.samples} paths/texel" if args.samples else "the commands' own paths"
    print(f"bench cores: {args.volume}, {paths}, threads "
          f"{', '.join(map(str, counts))} ({cores.available()} cores available), "
          f"{args.repeats} repeat(s); load average (1 min) {before[0]:.2f}", flush=True)
    results = {}
    with tempfile.TemporaryDirectory(prefix="isolume-cores-") as folder:
        for command in commands:
            runs = measure_command(args, command, counts, Path(folder), dask)
            one = next(r for r in runs if r["threads"] == 1 and r["scheduler"] is None)
            most = max((r for r in runs if r["scheduler"] is None), key=lambda r: r["threads"])
            results[command] = {"runs": runs,
                                "predicted": predictions(one["timeline"], most["timeline"]),
                                "inner": inner_factors(one["timeline"], most["timeline"]),
                                "inner_threads": most["threads"],
                                "measured_speedups": measured_speedups(runs)}
    after = os.getloadavg()
    print(f"load average (1 min) after: {after[0]:.2f}")
    if before[0] > BUSY_LOAD:
        print(f"note: load average {before[0]:.2f} before the runs: other processes shared "
              "the cores, so the runs with more threads (their walls, efficiencies, item "
              "durations and serial seconds, hence Amdahl's prediction) read worse than on "
              "an idle machine; the replay comes from the one-thread run")
    for command, result in results.items():
        print()
        print("\n".join(table(command, result["runs"], result["predicted"])))
        print("\n".join(whole_lines(command, result["runs"], result["predicted"])))
        print(inner_line(result["inner"], result["inner_threads"]))
        print(sameness_line(command, result["runs"]))
    settings = {k: v for k, v in vars(args).items() if isinstance(v, str | int | float | bool)}
    (out / "cores.json").write_text(json.dumps(
        {"settings": {**settings, "threads": counts, "commands": commands, "dask": dask},
         "available_cores": cores.available(), "load_average_before": list(before),
         "load_average_after": list(after), "predict_at": list(PREDICT_AT),
         "results": results}, indent=1))
    gantt_chart([r for result in results.values() for r in result["runs"]], out / "gantt.png")
    speedup_chart(results, out / "speedup.png")
    print()
    print(f"wrote {out / 'cores.json'}, {out / 'gantt.png'} and {out / 'speedup.png'}")
    return 0
