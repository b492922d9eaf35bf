"""``isolume chart``: speed against accuracy, charted (DESIGN §7).

Writes PNG charts into ``--out DIR``, each with a JSON file holding every number it plots
plus the settings that made it (`app.charts.builders` lists the charts; charts 1-4 by
default, chart 5 with ``--charts 5``). Chart 1's lattices take 16, 64, 256 (and 1024
without ``--quick``) paths per texel.

Error: relative RMSE of linear radiance against a per-pixel path-traced reference (the
baker's own integrator, `baking.reference`), over the pixels that both images mark as
surface and over their RGB values, ``sqrt(mean((img − ref)²)) / mean(ref)``
(`app.charts.metrics`). The reference gains samples until its own noise is at most 1/4 of
the smallest error charted, or until ``--ref-max-seconds`` of tracing, which the JSON then
says (`app.charts.tracing`).

Everything is rendered with the GL renderer on one headless context (`app.charts.scene`),
same mesh, camera and albedo for every image. Lattices (`app.charts.lattices`) and the
reference's state are kept in ``DIR/cache`` (or ``--cache``) and reused by later runs with
the same settings.

This module holds the command: its options (`add_arguments`), the volume it charts
(``--crop``, ``--downsample``) and the run (`run`).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from isolume.app.charts.builders import CHART_BUILDERS
from isolume.app.charts.lattices import BAKE_TIME, LatticeStore
from isolume.app.charts.lighting import local_lighting
from isolume.app.charts.metrics import image_entries
from isolume.app.charts.model import Chart, Plan, Run
from isolume.app.charts.output import write_chart
from isolume.app.charts.progress import say
from isolume.app.charts.scene import GLScene
from isolume.app.charts.tracing import NOISE_RATIO, Reference, settle_reference
from isolume.app.options import CLIError, isovalue, load_volume, parse_size
from isolume.baking.config import DEFAULT_BOUNCES
from isolume.volumes import cores

HELP = "charts of error against bake time, lattice resolution, lookups and shading modes"

DEFAULT_VOLUME = "synthetic:engine:64"
CHART_SCENE_ENV = "sky:sun=3"
"""The environment the charts are drawn under unless ``--env`` says otherwise: a sky with
a sun of irradiance 3 at the sky's default place (azimuth 45°, elevation 40°). Every
published chart (``docs/charts``, the figures of docs/performance.md and docs/baker.md)
was measured under it, so the charts keep it rather than the command line's default
lighting (`baking.config.DEFAULT_ENV`, a sun placed for the first picture's cast
shadows): a run with the default options reproduces them."""
SAMPLES = (16, 64, 256, 1024)
SAMPLES_QUICK = (16, 64, 256)
CHART_SAMPLES = 256
CHART_SAMPLES_QUICK = 64
REF_MAX_SECONDS = 1800.0
REF_MAX_SECONDS_QUICK = 300.0
CHARTS = ("1", "2", "3", "4", "5")


# -- options ----------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume chart``."""
    p.add_argument("volume", nargs="?", default=None,
                   help=f"volume file or synthetic:NAME[:SIZE] (default {DEFAULT_VOLUME})")
    p.add_argument("--dims", help="X,Y,Z for raw files whose name does not say")
    p.add_argument("--dtype", help="sample type for raw files, e.g. uint8, int16, float32")
    p.add_argument("--spacing", help="voxel size X,Y,Z (overrides the file)")
    p.add_argument("--crop", metavar="X0:X1,Y0:Y1,Z0:Z1",
                   help="chart a sub-volume (voxel index ranges, end exclusive)")
    p.add_argument("--downsample", type=int, default=1, metavar="F",
                   help="average F×F×F voxel blocks first (default 1: none)")
    p.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    p.add_argument("--out", required=True, help="folder for the PNG and JSON files")
    p.add_argument("--cache", help="folder for lattices and the reference state, reused by "
                   "later runs with the same settings (default OUT/cache)")
    p.add_argument("--quick", action="store_true",
                   help=f"samples {','.join(map(str, SAMPLES_QUICK))} (no 1024), "
                   f"{CHART_SAMPLES_QUICK} paths per texel for charts 2-4, "
                   f"reference capped at {REF_MAX_SECONDS_QUICK:g} s")
    p.add_argument("--size", default="128x128", help="WxH pixels of every image (default "
                   "128x128)")
    p.add_argument("--view", default="30,30", help="AZ,EL[,DIST]: degrees, diagonals")
    p.add_argument("--env", default=CHART_SCENE_ENV,
                   help=f"environment: constant:R,G,B | sky[:k=v,...] | FILE.exr/.hdr "
                   f"(default {CHART_SCENE_ENV})")
    p.add_argument("--bounces", type=int, default=DEFAULT_BOUNCES,
                   help=f"diffuse bounces (default {DEFAULT_BOUNCES})")
    p.add_argument("--albedo", type=float, default=0.8, help="gray diffuse reflectance")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--workers", type=int, default=None, help="threads (default: all cores)")
    p.add_argument("--gl", default="egl", choices=["egl", "osmesa", "auto"],
                   help="headless GL backend (default egl)")
    p.add_argument("--samples", help="paths per texel of chart 1, comma-separated "
                   "(overrides --quick's list)")
    p.add_argument("--chart-samples", type=int, default=None,
                   help="paths per texel of the lattices of charts 2-4")
    p.add_argument("--charts", default=",".join(CHARTS[:4]),
                   help=f"which charts of {','.join(CHARTS)}, e.g. 1,4 (default 1-4)")
    p.add_argument("--ref-spp", type=int, default=64, help="first reference spp (default 64)")
    p.add_argument("--ref-max-seconds", type=float, default=None,
                   help="cap on reference tracing time (default "
                   f"{REF_MAX_SECONDS:g}, {REF_MAX_SECONDS_QUICK:g} with --quick)")
    p.add_argument("--draws", type=int, default=10, help="timed frames per mode (≥ 10)")


def _plan(args: argparse.Namespace) -> Plan:
    """Resolve and check the counts of ``isolume chart``."""
    samples = SAMPLES_QUICK if args.quick else SAMPLES
    if args.samples:
        try:
            samples = tuple(sorted({int(v) for v in args.samples.split(",")}))
        except ValueError:
            raise CLIError(f"--samples {args.samples!r}: expected integers, e.g. 16,64"
                           ) from None
    chart_samples = args.chart_samples or (CHART_SAMPLES_QUICK if args.quick else CHART_SAMPLES)
    charts = tuple(c.strip() for c in args.charts.split(",") if c.strip())
    if not charts or set(charts) - set(CHARTS):
        raise CLIError(f"--charts {args.charts!r}: expected numbers among {','.join(CHARTS)}")
    if min(samples) < 1 or chart_samples < 1 or args.ref_spp < 2:
        raise CLIError("sample counts must be ≥ 1 (the reference's ≥ 2)")
    if args.draws < 10:
        raise CLIError(f"--draws {args.draws}: at least 10 frames are timed per mode")
    if not 0 < args.albedo <= 1:
        raise CLIError(f"--albedo {args.albedo:g}: expected a reflectance in (0, 1]")
    cap = args.ref_max_seconds
    cap = (REF_MAX_SECONDS_QUICK if args.quick else REF_MAX_SECONDS) if cap is None else cap
    return Plan(samples, chart_samples, charts, args.ref_spp, float(cap), args.draws)


# -- the volume -------------------------------------------------------------------------
def _prepare_volume(args: argparse.Namespace):
    """(volume, notes): the volume to chart after --crop and --downsample."""
    from isolume import volumes

    args.volume = args.volume or DEFAULT_VOLUME
    volume = volumes.crop_downsample(load_volume(args), args.crop, args.downsample)
    notes = []
    if args.crop:
        notes.append(f"sub-volume: voxels {args.crop} (x, y, z; end exclusive)")
    if args.downsample > 1:
        notes.append(f"downsampled by {args.downsample} per axis (block means)")
    return volume, notes


# -- the command ------------------------------------------------------------------------
def _settings(args, volume, iso: float, plan: Plan, notes: list[str], run: Run) -> dict:
    """The settings block of every JSON."""
    lo, hi = volume.value_range
    return {
        "volume": volume.source or volume.name, "dims_xyz": list(volume.shape_xyz),
        "spacing": list(volume.spacing), "value_range": [lo, hi], "preprocessing": notes,
        "iso": iso, "size": list(run.gl.size), "view": args.view, "env": args.env,
        "bounces": args.bounces, "albedo": args.albedo, "seed": args.seed,
        "quick": args.quick, "samples": list(plan.samples),
        "chart_samples": plan.chart_samples, "triangles": len(run.gl.mesh.faces),
        "gl_renderer": run.gl.gl_renderer, "workers": args.workers or cores.threads(),
        "cpu_count": cores.available(), "load_average_1min_at_end": os.getloadavg()[0],
        "error_metric": "sqrt(mean((img - ref)^2)) / mean(ref) over the RGB values of the "
                        "pixels both images mark as surface (linear radiance)",
        "bake_time": BAKE_TIME,
        **run.facts,
    }


def _cache_folder(args: argparse.Namespace, out: Path) -> Path:
    return Path(args.cache) if args.cache else out / "cache"


def _make_run(args, volume, iso: float, plan: Plan, out: Path) -> Run:
    from isolume.app.render.camera import parse_view
    from isolume.app.render.renderer import default_camera
    from isolume.baking.config import BakeConfig

    try:
        camera = default_camera(volume, parse_view(args.view))
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    size = parse_size(args.size)
    origins, dirs = camera.primary_rays(*size)
    config = BakeConfig(mode="irradiance", samples=plan.chart_samples, bounces=args.bounces,
                        albedo=(args.albedo,) * 3, env=args.env, seed=args.seed)
    lighting = local_lighting(args.env)
    gl = GLScene(volume, iso, camera, size, args.gl, lighting, args.albedo, args.env)
    store = LatticeStore(volume, _cache_folder(args, out), args.workers)
    return Run(volume, iso, origins, dirs, config, plan, store, gl, args.workers)


def run(args: argparse.Namespace) -> int:
    """Make the charts; returns the exit status."""
    from isolume.app.render.images import output_folder

    out = output_folder(args.out)
    plan = _plan(args)
    volume, notes = _prepare_volume(args)
    iso = isovalue(volume, args.iso)
    began, load = time.perf_counter(), os.getloadavg()[0]
    chart_run = _make_run(args, volume, iso, plan, out)
    try:
        if chart_run.gl.mesh.empty:
            raise CLIError(f"no surface at isovalue {iso:g}: {chart_run.gl.mesh.message}")
        charts = []
        for number in plan.charts:
            charts.append(CHART_BUILDERS[number](chart_run))
            say(f"chart {number} rendered ({time.perf_counter() - began:.0f} s)")
        ref = Reference(chart_run, _cache_folder(args, out) / "reference.state.npz")
        try:
            reference = settle_reference(ref, charts, chart_run.images, plan)
        finally:
            ref.close()
        settings = _settings(args, volume, iso, plan, notes, chart_run)
        settings["total_seconds"] = time.perf_counter() - began
        settings["load_average_1min_at_start"] = load
        for chart in charts:
            png = write_chart(chart, out, settings, reference)
            print(f"wrote {png} and {png.with_suffix('.json').name}")
    finally:
        chart_run.gl.release()
    _report(reference, charts)
    return 0


def _report(reference: dict, charts: list[Chart]) -> None:
    """One line on the reference rule, one per chart with its key figures."""
    rule = "holds" if reference["holds"] else (
        f"NOT met within the {reference['cap_seconds']:g} s cap (needs ~"
        f"{reference['spp_needed']} spp)")
    print(f"reference {reference['spp']} spp in {reference['seconds']:.0f} s: noise "
          f"{reference['noise']:.2%}, smallest error {reference['smallest_error']:.2%}; "
          f"rule (noise <= {NOISE_RATIO:g} x smallest) {rule}")
    for chart in charts:
        entries = image_entries(chart.data)
        figures = ", ".join(f"{_entry_label(e)} {e['error']:.2%}" for e in entries
                            if e.get("error") is not None)
        print(f"{chart.name}: {figures}")


def _entry_label(entry: dict) -> str:
    """A short name of a charted image for the summary line."""
    image = entry["image"]
    if image.startswith("path_traced/"):
        return f"pt {entry['spp']}spp"
    return image.split("/", 1)[1]
