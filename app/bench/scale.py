"""``isolume bench scale``: how peak memory and wall time grow with the volume.

For each size N (samples along the longest axis) and each source — ``synthetic`` (the
built-in engine) and ``real`` (a scan, by default the foot CT of ``../shared/data``,
upsampled trilinearly) — the volume is written as a uint8 raw file (layer by layer, so a
volume larger than memory can be made), then each command runs as a child process, as a
user would run it, with its defaults:

* ``info``; ``render`` (the view's global illumination, ``--size``, 512² by default);
* ``bake`` (``--samples``, 16 by default, to a lattice file), then ``render --lattice``;
* ``view``: the viewer under a display (Xvfb where none is set) until global
  illumination is on screen (its script's ``wait-gi``: the lazy bake's first preview
  pass), then a frame and a screenshot: the seconds from the program's start to the
  first global illumination on screen, as the script reports it (the run itself goes on
  to the screenshot: the full-resolution surface, drawn once more off-screen).

Peak memory is the largest sum of the resident memory of the command's processes
(sampled every 50 ms: the viewer's bake process counts). A run whose memory or time,
extrapolated from the smaller sizes of the same command (a power law through the last
two), would pass ``--memory-cap`` or ``--time-cap`` is skipped and says why. The
exponents of memory and time against the voxel count, and against the texels the
command lit (render: the view's texels; bake and render ``--lattice``: the lattice's
active texels), come from a least-squares fit over the sizes that ran. Writes
``scale.json``, ``table.txt`` and the chart ``scale.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from isolume.app.render.images import output_folder
from isolume.volumes.writing import atomic_write

HELP = ("peak memory and wall time of info, render, bake, render --lattice and the viewer "
        "against the volume's size, with their exponents")
SIZES = (128, 256, 512, 1024)
COMMANDS = ("info", "render", "bake", "render_lattice", "view")
SOURCES = ("synthetic", "real")
REAL = "foot_zfp_256x256x256_uint8.raw.gz"
"""The scan of ``../shared/data/volumes`` upsampled for the ``real`` source."""
SAMPLE_S = 0.05
"""Seconds between two readings of the processes' resident memory."""
LAYERS = 16
"""z layers written at a time."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), metavar="N",
                   help="samples along the longest axis (default 128 256 512 1024)")
    p.add_argument("--sources", nargs="+", choices=SOURCES, default=list(SOURCES),
                   help="synthetic (the built-in engine) and/or real (a scan upsampled) "
                   "(default both)")
    p.add_argument("--commands", nargs="+", choices=COMMANDS, default=list(COMMANDS),
                   help="what to measure (default all)")
    p.add_argument("--real", metavar="VOLUME",
                   help=f"the scan to upsample (default ../shared/data/volumes/{REAL})")
    p.add_argument("--samples", type=int, default=16, help="bake paths per texel (default 16)")
    p.add_argument("--size", default="512x512", help="render and viewer picture WxH "
                   "(default 512x512)")
    p.add_argument("--memory-cap", type=float, metavar="GB",
                   help="skip runs extrapolated to need more (default 80 %% of this "
                   "machine's memory)")
    p.add_argument("--time-cap", type=float, default=1800.0, metavar="S",
                   help="skip runs extrapolated to take longer, stop a run that does "
                   "(default 1800)")
    p.add_argument("--work", metavar="DIR",
                   help="keep the volumes and lattices here, and reuse them (default: a "
                   "temporary folder, removed)")
    p.add_argument("--out", default="scale", metavar="DIR",
                   help="folder for scale.json, table.txt and scale.png (default scale)")


# -- the volumes ------------------------------------------------------------------------------
def write_synthetic(size: int, folder: Path) -> Path:
    """``synthetic:engine`` at `size` as uint8 (density × 255) ``NAME_XxYxZ_uint8.raw``."""
    from isolume.volumes import synthetic

    z, y, x = synthetic.shape("engine", size)
    path = folder / f"engine{size}_{x}x{y}x{z}_uint8.raw"
    if not path.exists():
        def write(tmp: str) -> None:
            with open(tmp, "wb") as out:
                for k0 in range(0, z, LAYERS):
                    part = synthetic.layers("engine", size, k0, min(k0 + LAYERS, z))
                    out.write(np.rint(np.clip(part, 0, 1) * 255).astype(np.uint8).tobytes())

        atomic_write(path, write, "volume")
    return path


def write_upsampled(source: str, size: int, folder: Path) -> Path:
    """The scan `source` resampled trilinearly to `size` samples along its longest axis
    (the same box), as uint8 ``NAME_XxYxZ_uint8.raw``."""
    from scipy import ndimage

    from isolume import volumes

    volume = volumes.load(source)
    samples = np.asarray(volume.data, np.float32)  # trilinear on float32 samples
    shape = np.array(volume.data.shape)
    new = np.maximum(2, np.rint((shape - 1) * (size - 1) / (shape.max() - 1)).astype(int) + 1)
    z, y, x = (int(n) for n in new)
    path = folder / f"{volume.name}{size}_{x}x{y}x{z}_uint8.raw"
    if not path.exists():
        steps = (shape - 1) / np.maximum(new - 1, 1)

        def write(tmp: str) -> None:
            with open(tmp, "wb") as out:
                for k0 in range(0, z, LAYERS):
                    k = np.arange(k0, min(k0 + LAYERS, z))
                    grid = np.meshgrid(k * steps[0], np.arange(y) * steps[1],
                                       np.arange(x) * steps[2], indexing="ij")
                    part = ndimage.map_coordinates(samples, grid, order=1, mode="nearest")
                    out.write(np.rint(np.clip(part, 0, 255)).astype(np.uint8).tobytes())

        atomic_write(path, write, "volume")
    return path


# -- one run ----------------------------------------------------------------------------------
@dataclass
class Run:
    """One command on one volume.

    Attributes:
        source, size, command: what ran; voxels: the volume's sample count.
        status: "ok", "failed", "timeout" or "skipped".
        seconds: wall time (the viewer: to global illumination on screen, `first_gi`);
        peak_mb: largest sum of resident memory, MiB; texels: what it lit (None: not
        told); note: why it was skipped or failed, or what it printed last.
    """

    source: str
    size: int
    command: str
    voxels: int
    status: str = "ok"
    seconds: float | None = None
    peak_mb: float | None = None
    texels: int | None = None
    note: str = ""


def measure(argv: list[str], timeout: float, marker: Path | None = None,
            env: dict[str, str] | None = None) -> tuple[str, float, float, str]:
    """Run `argv`; returns (status, seconds, peak MiB of its process tree's resident
    memory, its stdout + stderr). `marker`: the seconds are those until that file exists
    (the process still runs on to its end)."""
    import psutil

    began = time.perf_counter()
    with tempfile.TemporaryFile() as log:
        child = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env)
        proc = psutil.Process(child.pid)
        peak, seen = 0, None
        status = "ok"
        while child.poll() is None:
            peak = max(peak, _tree_rss(proc))
            if marker is not None and seen is None and marker.exists():
                seen = time.perf_counter() - began
            if time.perf_counter() - began > timeout:
                _stop(proc)
                status = "timeout"
                break
            time.sleep(SAMPLE_S)
        child.wait()
        seconds = time.perf_counter() - began
        if status == "ok" and child.returncode != 0:
            status = "failed"
        if marker is not None:
            seconds = seen if seen is not None else (seconds if marker.exists() else math.nan)
        log.seek(0)
        text = log.read().decode(errors="replace")
    return status, seconds, peak / 2**20, text


def _tree_rss(proc) -> int:
    """Resident bytes of `proc` and its descendants (0 for those already gone)."""
    import psutil

    total = 0
    try:
        family = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return 0
    for p in family:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def _stop(proc) -> None:
    """Kill `proc` and its descendants."""
    import psutil

    try:
        family = [*proc.children(recursive=True), proc]
    except psutil.Error:
        return
    for p in family:
        try:
            p.kill()
        except psutil.Error:
            pass


TEXELS = {
    "render": re.compile(r"global illumination: ([\d,]+) texels"),
    "bake": re.compile(r"([\d,]+) of [\d,]+ texels active"),
}
"""What each command prints about the texels it lit."""
FIRST_GI = re.compile(r"wait-gi done ([\d.]+) s after the start")
"""What the viewer's script prints when global illumination is on screen."""


def first_gi(text: str) -> float | None:
    """Seconds from the viewer's start to global illumination on screen, as its script
    said (None: it did not)."""
    found = FIRST_GI.findall(text)
    return float(found[-1]) if found else None


def texels_of(command: str, text: str) -> int | None:
    """The texels `command` lit, as its output says (None: it says nothing)."""
    pattern = TEXELS.get(command)
    found = pattern.findall(text) if pattern else []
    return int(found[-1].replace(",", "")) if found else None


# -- extrapolation and fits ---------------------------------------------------------------
def predicted(runs: list[Run], source: str, command: str, voxels: int
              ) -> tuple[float | None, float | None]:
    """(peak MiB, seconds) of `command` on `voxels` extrapolated from its finished runs on
    `source` (a power law through the last two; one run: proportional); None: none ran."""
    done = [r for r in runs if r.source == source and r.command == command
            and r.status == "ok" and r.peak_mb and r.seconds]
    if not done:
        return None, None
    if len(done) == 1:
        ratio = voxels / done[0].voxels
        return done[0].peak_mb * ratio, done[0].seconds * ratio
    a, b = done[-2], done[-1]
    out = []
    for attr in ("peak_mb", "seconds"):
        slope = math.log(getattr(b, attr) / getattr(a, attr)) / math.log(b.voxels / a.voxels)
        out.append(getattr(b, attr) * (voxels / b.voxels) ** max(slope, 0.0))
    return out[0], out[1]


def exponent(xs: list[float], ys: list[float]) -> float | None:
    """Least-squares slope of log y against log x (None: fewer than two distinct x)."""
    if len(set(xs)) < 2:
        return None
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def exponents(runs: list[Run]) -> list[dict[str, Any]]:
    """Per source and command: the exponents of memory and time against voxels and
    against texels, over the runs that finished."""
    rows = []
    for source in dict.fromkeys(r.source for r in runs):
        for command in COMMANDS:
            done = [r for r in runs if r.source == source and r.command == command
                    and r.status == "ok" and r.peak_mb and r.seconds]
            if len(done) < 2:
                continue
            row = {"source": source, "command": command,
                   "sizes": [r.size for r in done]}
            for x in ("voxels", "texels"):
                xs = [getattr(r, x) for r in done]
                if None in xs:
                    continue
                row[f"memory_vs_{x}"] = exponent(xs, [r.peak_mb for r in done])
                row[f"time_vs_{x}"] = exponent(xs, [r.seconds for r in done])
            rows.append(row)
    return rows


# -- the sweep --------------------------------------------------------------------------------
@dataclass
class Plan:
    """What the sweep runs, and its limits."""

    sizes: list[int]
    sources: list[str]
    commands: list[str]
    real: str
    samples: int
    size: str
    memory_mb: float
    time_cap: float
    work: Path
    out: Path
    display: str | None = None
    runs: list[Run] = field(default_factory=list)


def _cli(*words: str) -> list[str]:
    """The argv of ``isolume WORDS`` in this interpreter."""
    return [sys.executable, "-c", "import sys; from isolume.app.cli import main; "
            "sys.exit(main())", *words]


def _argv(plan: Plan, command: str, volume: Path, lattice: Path, shot: Path) -> list[str]:
    """The command line of `command` on `volume`."""
    if command == "info":
        return _cli("info", str(volume))
    if command == "render":
        return _cli("render", str(volume), "--size", plan.size,
                    "--out", str(plan.work / "render.png"))
    if command == "bake":
        return _cli("bake", str(volume), "--samples", str(plan.samples), "--out", str(lattice))
    if command == "render_lattice":
        return _cli("render", str(volume), "--lattice", str(lattice), "--size", plan.size,
                    "--out", str(plan.work / "render_lattice.png"))
    script = plan.work / "first_gi.txt"
    script.write_text(f"wait-gi {plan.time_cap:g}\nframes 1\nscreenshot {shot}\nquit\n")
    return _cli("view", str(volume), "--size", plan.size, "--script", str(script))


def run_one(plan: Plan, source: str, size: int, command: str, volume: Path,
            voxels: int) -> Run:
    """Measure `command` on `volume`, or skip it (too big, no display, no lattice)."""
    run = Run(source, size, command, voxels)
    lattice = plan.work / f"{volume.stem}.npz"
    memory, seconds = predicted(plan.runs, source, command, voxels)
    why = ""
    if memory is not None and memory > plan.memory_mb:
        why = f"needs about {memory / 1024:.1f} GB (cap {plan.memory_mb / 1024:.1f} GB)"
    elif seconds is not None and seconds > plan.time_cap:
        why = f"takes about {seconds:.0f} s (cap {plan.time_cap:.0f} s)"
    elif command == "view" and plan.display is None:
        why = "no display and no Xvfb"
    elif command == "render_lattice" and not lattice.exists():
        why = "no lattice (the bake did not run)"
    if why:
        run.status, run.note = "skipped", why
        return run
    shot = plan.work / "first_gi.png"
    shot.unlink(missing_ok=True)
    env = dict(os.environ, DISPLAY=plan.display) if plan.display else None
    status, secs, peak, text = measure(_argv(plan, command, volume, lattice, shot),
                                       plan.time_cap, shot if command == "view" else None,
                                       env)
    run.status, run.seconds, run.peak_mb = status, secs, peak
    if command == "view" and status == "ok":
        run.seconds = first_gi(text)
    if command == "render_lattice":  # the lattice's active texels, as its bake said
        run.texels = next((r.texels for r in reversed(plan.runs) if r.source == source
                           and r.size == size and r.command == "bake"), None)
    else:
        run.texels = texels_of(command, text)
    if status != "ok":
        run.note = (text.strip().splitlines() or [""])[-1][:200]
    return run


def volume_for(plan: Plan, source: str, size: int) -> tuple[Path, int]:
    """(the raw file of `source` at `size`, its voxel count), written when missing."""
    path = (write_synthetic(size, plan.work) if source == "synthetic"
            else write_upsampled(plan.real, size, plan.work))
    x, y, z = (int(v) for v in re.search(r"_(\d+)x(\d+)x(\d+)_", path.name).groups())
    return path, x * y * z


ROW = "{:<9} {:>5} {:<15} {:>12} {:>8} {:>9} {:>11}  {}"


def row_text(run: Run) -> str:
    """One line of the table."""
    return ROW.format(run.source, run.size, run.command, f"{run.voxels:,}",
                      "-" if run.seconds is None or math.isnan(run.seconds)
                      else f"{run.seconds:.1f}",
                      "-" if run.peak_mb is None else f"{run.peak_mb:.0f}",
                      "-" if run.texels is None else f"{run.texels:,}",
                      run.status + (f": {run.note}" if run.note else ""))


def sweep(plan: Plan) -> None:
    """Every size, source and command, smallest first; a row printed as each ends."""
    print(ROW.format("source", "N", "command", "voxels", "wall s", "peak MiB", "texels",
                     "status"), flush=True)
    for size in sorted(plan.sizes):
        for source in plan.sources:
            volume, voxels = volume_for(plan, source, size)
            for command in plan.commands:
                run = run_one(plan, source, size, command, volume, voxels)
                plan.runs.append(run)
                print(row_text(run), flush=True)
            (plan.work / f"{volume.stem}.npz").unlink(missing_ok=True)


def write_outputs(plan: Plan, fits: list[dict[str, Any]]) -> None:
    """scale.json, table.txt and scale.png in `plan.out` (made by `output_folder`)."""
    settings = {k: v for k, v in asdict(plan).items() if k not in ("runs", "work", "out")}
    (plan.out / "scale.json").write_text(json.dumps(
        {"settings": settings, "runs": [asdict(r) for r in plan.runs], "exponents": fits},
        indent=1, default=str))
    lines = [ROW.format("source", "N", "command", "voxels", "wall s", "peak MiB", "texels",
                        "status"), *map(row_text, plan.runs), "", *map(fit_text, fits)]
    (plan.out / "table.txt").write_text("\n".join(lines) + "\n")
    chart(plan.runs, plan.out / "scale.png")


def fit_text(fit: dict[str, Any]) -> str:
    """One line of exponents."""
    parts = [f"{k.replace('_vs_', ' ~ ')}^{v:.2f}" for k, v in fit.items()
             if "_vs_" in k and v is not None]
    return f"{fit['source']:<9} {fit['command']:<15} " + ", ".join(parts)


def chart(runs: list[Run], path: Path) -> None:
    """Log-log chart: peak memory and wall time against voxels, a colour per command, a
    line per source (synthetic solid, real dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for (attr, label), ax in zip((("peak_mb", "peak memory, MiB"), ("seconds", "wall, s")),
                                 axes, strict=True):
        for source in dict.fromkeys(r.source for r in runs):
            for command in COMMANDS:
                done = [r for r in runs if r.source == source and r.command == command
                        and r.status == "ok" and getattr(r, attr)]
                if done:
                    ax.loglog([r.voxels for r in done], [getattr(r, attr) for r in done],
                              "o-" if source == "synthetic" else "s--",
                              color=f"C{COMMANDS.index(command)}",
                              label=f"{command} ({source})")
        ax.set_xlabel("voxels")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _display() -> tuple[str | None, subprocess.Popen | None]:
    """(DISPLAY for the viewer, the Xvfb started for it or None)."""
    if os.environ.get("DISPLAY"):
        return os.environ["DISPLAY"], None
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        return None, None
    for n in range(90, 110):
        if Path(f"/tmp/.X{n}-lock").exists():
            continue
        server = subprocess.Popen([xvfb, f":{n}", "-screen", "0", "1280x1024x24", "-nolisten",
                                   "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(1.0)
        if server.poll() is None:
            return f":{n}", server
    return None, None


def run(args: argparse.Namespace) -> int:
    """Run the sweep; returns the exit status."""
    import psutil

    from isolume.app.bench.view import data_folder
    from isolume.app.options import CLIError

    if "real" in args.sources and args.real is None:
        folder, _ = data_folder(None)
        args.real = str(folder / "volumes" / REAL)
        if not Path(args.real).exists():
            raise CLIError(f"bench scale: {args.real} not found; give --real VOLUME or "
                           "--sources synthetic")
    if min(args.sizes) < 16 or max(args.sizes) > 1024:
        raise CLIError(f"--sizes {args.sizes}: expected 16 to 1024")
    cap = args.memory_cap * 1024 if args.memory_cap else 0.8 * psutil.virtual_memory().total / 2**20
    keep = args.work is not None
    work = Path(args.work) if keep else Path(tempfile.mkdtemp(prefix="isolume-scale-"))
    work.mkdir(parents=True, exist_ok=True)
    display, server = _display() if "view" in args.commands else (None, None)
    plan = Plan(args.sizes, args.sources, args.commands, args.real, args.samples, args.size,
                cap, args.time_cap, work, output_folder(args.out), display)
    try:
        sweep(plan)
    finally:
        if server is not None:
            server.terminate()
        if not keep:
            shutil.rmtree(work, ignore_errors=True)
    fits = exponents(plan.runs)
    print()
    for fit in fits:
        print(fit_text(fit))
    write_outputs(plan, fits)
    print(f"wrote {plan.out / 'scale.json'}, table.txt and scale.png")
    return 0
