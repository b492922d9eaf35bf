"""``isolume bench accuracy``: the lighting accuracy of the default picture, on every scan.

For each volume (by default every volume file in the data folder's ``volumes/``: ``--data``,
else ``$ISOLUME_DATA``, else ``../shared/data`` from the current folder or beside the
repository) and each isovalue ``isolume info`` suggests (`volumes.suggest_isovalues`, on
the volume as loaded, turned by ``--up`` where asked), two pictures are measured:

* **render**: what ``isolume render VOLUME --size WxH`` draws: the view's traced global
  illumination (`app.render.offscreen.render_volume` with no lattice, lit by
  `app.options.view_light` from the render command's defaults);
* **bake**: a bake with ``isolume bake``'s defaults (`app.options.bake_config`: the
  default sky, a texel error of 0.02 at 32 paths a traced texel, 2 bounces, scale 1),
  or with ``--paths N`` (exactly N a texel), ``--target-error E`` or ``--texel-error E``,
  restricted, for time, to the iso range a lazy bake serves for that isovalue
  (`baking.lazy.view_iso_range`: ±3 % of the data range), then the picture drawn with
  that lattice; its row records the paths it traced and its bytes. With ``--bake-range
  default``, one bake of each volume over ``isolume bake``'s default iso range
  (`baking.plan.default_iso_range`) draws every isovalue measured — with ``--isovalues
  across:N``, N spread evenly across that range: one lattice serving every isovalue, as
  the method means it to — and its rows carry the bake's paths, seconds and bytes with
  the count of cases that share them (``shared_by``: sums divide by it);

both against the per-pixel path-traced reference of ``isolume reference``
(`baking.reference.ReferenceTracer`) with the same camera, size and lighting (the seed
one above the render's, so their noise is independent). The reference starts at
`START_SPP` samples per pixel and gains samples until its own noise (from its per-pixel
standard errors) is at most a quarter of the smaller error it measures, or up to
``--ref-spp``. References are kept in ``--cache DIR`` (`reference_cache`), keyed by the
reference tracer's identity (volume, isovalue, camera rays, lighting), and a later sweep
starts from them: a curve of bake settings costs bakes, not references. The figures are
those of `app.bench.accuracy_metrics`; the output that of `app.bench.accuracy_output`.

Volumes larger than ``--max-size`` along an axis are reduced by block means of F³ voxels
(`volumes.crop_downsample`) after the isovalues are suggested. A volume that
cannot be read, or a case that fails, is one line on stderr and a record in the JSON;
the sweep goes on (exit status 1 when anything failed).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume.app.bench.accuracy_output import Report
from isolume.app.bench.accuracy_reference import (
    START_SPP,
    AccuracyError,
    Truth,
    settle_reference,
)
from isolume.app.render.images import output_folder
from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    from isolume.app.bench.accuracy_output import Tile
    from isolume.baking.config import BakeConfig
    from isolume.volumes import Volume

HELP = "lighting accuracy of the default render and bake against path tracing, every scan"
DEFAULT_MAX_SIZE = 128
DEFAULT_SIZE = "128x128"
DEFAULT_REF_SPP = 32768
"""Cap on the reference's samples per pixel."""
VOLUME_SUFFIXES = (".raw.gz", ".raw", ".nrrd", ".nhdr", ".mhd", ".mha", ".nii.gz", ".nii",
                   ".npy", ".npz", ".tif", ".tiff")
"""The file names a folder's volumes end with (those `volumes.load` reads by suffix)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume bench accuracy``."""
    from isolume.app.render.view_gi import SPREADS

    p.add_argument("volumes", nargs="*", metavar="VOLUME|FOLDER",
                   help="volume files, synthetic:NAME[:SIZE] specs, or folders of volume "
                   "files (default: every volume in DATA/volumes)")
    p.add_argument("--data", metavar="DIR",
                   help="data folder holding volumes/ (default $ISOLUME_DATA, else "
                   "../shared/data from the current folder or beside the repository)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="folder for accuracy.json, table.txt and accuracy.png")
    p.add_argument("--only", metavar="NAME[,NAME]",
                   help="only the volumes whose file name contains one of these")
    p.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE, metavar="N",
                   help="block-mean each volume until its largest dimension is <= N "
                   f"(default {DEFAULT_MAX_SIZE}; 0: as loaded)")
    p.add_argument("--size", default=DEFAULT_SIZE, help=f"WxH pixels (default {DEFAULT_SIZE})")
    p.add_argument("--ref-spp", type=int, default=DEFAULT_REF_SPP, metavar="N",
                   help=f"cap on the reference's samples per pixel (default {DEFAULT_REF_SPP})")
    p.add_argument("--paths", type=int, default=None, metavar="N",
                   help="paths per texel of the render's and the bake's light (the "
                   "render's on average, as --render-spread places them; the bake's "
                   "exactly N at every texel without --texel-error/--target-error; default "
                   "theirs)")
    p.add_argument("--render-spread", choices=SPREADS, default=SPREADS[0],
                   help="the render's paths placed where the picture's noise is, as render "
                   "does (noise, the default), or the same number at every texel (even)")
    p.add_argument("--target-error", type=float, default=None, metavar="E",
                   help="the bake's noise target, as bake's --target-error (with --paths: "
                   "its minimum paths)")
    p.add_argument("--texel-error", type=float, metavar="E", help="as bake's --texel-error")
    p.add_argument("--scale", type=float, default=1.0, metavar="S",
                   help="the bake's lattice texels per voxel, as bake's --scale (default 1)")
    p.add_argument("--cache", default=None, metavar="DIR|none",
                   help="folder of the references kept for later sweeps (default "
                   "$XDG_CACHE_HOME/isolume/references, else ~/.cache/isolume/references; "
                   "none: keep none)")
    p.add_argument("--skip-bake", action="store_true", help="measure the render only")
    p.add_argument("--isovalues", type=isovalue_rule, default="all",
                   metavar="first|all|across:N",
                   help="the first suggested isovalue, all of them (default), or N spread "
                   "evenly across the iso range isolume bake bakes by default (the "
                   "suggested isovalues with a quarter of their spread on either side)")
    p.add_argument("--bake-range", choices=["view", "default"], default="view",
                   help="view (the default): each case's own bake over +-3 %% of the data "
                   "range around its isovalue, as the viewer bakes; default: one bake of "
                   "each volume over isolume bake's default iso range, drawn at every "
                   "isovalue measured")
    p.add_argument("--up", action="append", metavar="[NAME=]AXIS",
                   help="turn the volumes (whose name contains NAME) so that AXIS points up, "
                   "as render's --up (repeatable)")
    p.add_argument("--view", default="30,30", help="AZ,EL[,DIST] as render (default 30,30)")
    p.add_argument("--workers", type=int, default=None, help="threads (default: all cores)")
    p.add_argument("--gl", default="auto", choices=["auto", "egl", "osmesa"],
                   help="headless GL: EGL, OSMesa, or whichever works (auto)")


# -- settings --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Sweep:
    """The sweep's settings, checked.

    Attributes:
        size: (width, height) pixels; view: (azimuth, elevation, distance or None).
        max_size: largest dimension kept, voxels (0: no reduction).
        ref_spp: cap on the reference's samples per pixel.
        paths: paths per texel of the render and the bake (None: their defaults);
            render_spread: how the render places its paths (`app.render.view_gi.SPREADS`).
        target_error: the bake's noise target (None: the bake's default, or exactly
            `paths`); texel_error: its texel error (None: none); scale: its texels per voxel.
        cache: the folder of kept references (None: none kept); up: ([NAME], AXIS) rules
            of ``--up``; progress: progress bars on stderr.
        first_only, across: ``--isovalues`` first, or across:N (N; else 0); bake_range:
            ``--bake-range`` ("view" or "default").
    """

    size: tuple[int, int]
    view: tuple[float, float, float | None]
    view_text: str
    max_size: int
    ref_spp: int
    paths: int | None
    render_spread: str
    target_error: float | None
    texel_error: float | None
    scale: float
    cache: Path | None
    skip_bake: bool
    first_only: bool
    across: int
    bake_range: str
    up: tuple[tuple[str, str], ...]
    workers: int | None
    gl: str
    progress: bool


def sweep_of(args: argparse.Namespace) -> Sweep:
    """The `Sweep` of the command line.

    Raises:
        CLIError: a bad count, size, view or axis (one line).
    """
    from isolume.app.options import CLIError, parse_size
    from isolume.app.render.camera import parse_view

    if args.max_size < 0 or args.max_size == 1:
        raise CLIError(f"--max-size {args.max_size}: expected 0 (as loaded) or at least 2")
    if args.ref_spp < 2:
        raise CLIError(f"--ref-spp {args.ref_spp}: expected at least 2 samples per pixel")
    if args.paths is not None and not 1 <= args.paths <= 4096:
        raise CLIError(f"--paths {args.paths}: expected 1 to 4096 paths per texel")
    try:
        view = parse_view(args.view)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    return Sweep(parse_size(args.size), view, args.view, args.max_size, args.ref_spp,
                 args.paths, args.render_spread, args.target_error, args.texel_error,
                 args.scale,
                 reference_cache(args.cache), args.skip_bake, args.isovalues == "first",
                 across_count(args.isovalues), args.bake_range, parse_up_rules(args.up),
                 args.workers, args.gl, sys.stderr.isatty())


def isovalue_rule(text: str) -> str:
    """``--isovalues``: "first", "all" or "across:N" (N ≥ 1).

    Raises:
        argparse.ArgumentTypeError: anything else.
    """
    if text in ("first", "all") or (text.startswith("across:")
                                    and text[7:].isdigit() and int(text[7:]) >= 1):
        return text
    raise argparse.ArgumentTypeError(f"{text!r}: expected first, all or across:N with N "
                                     "at least 1")


def across_count(rule: str) -> int:
    """N of an ``--isovalues`` rule "across:N", else 0."""
    return int(rule[7:]) if rule.startswith("across:") else 0


def reference_cache(text: str | None) -> Path | None:
    """The folder of kept references that ``--cache`` names ("none": None), made if
    missing.

    Raises:
        CLIError: the folder cannot be made.
    """
    import os


    if text is not None and text.lower() == "none":
        return None
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    folder = base / "isolume" / "references" if text is None else Path(text).expanduser()
    return output_folder(folder, "--cache")


def parse_up_rules(values: list[str] | None) -> tuple[tuple[str, str], ...]:
    """(NAME, AXIS) of each ``--up [NAME=]AXIS`` (NAME "" for every volume).

    Raises:
        CLIError: an axis that is not one of `volumes.UP_AXES`.
    """
    from isolume import volumes
    from isolume.app.options import CLIError

    rules = []
    for text in values or ():
        name, _, axis = text.rpartition("=")
        if axis.strip().lower().replace("+", "") not in volumes.UP_AXES:
            raise CLIError(f"--up {text!r}: expected [NAME=]AXIS with AXIS one of "
                           f"{', '.join(volumes.UP_AXES)}")
        rules.append((name.strip(), axis.strip()))
    return tuple(rules)


def up_axis(name: str, rules: tuple[tuple[str, str], ...]) -> str | None:
    """The axis the last rule matching `name` (case-insensitive substring) turns up."""
    axis = None
    for pattern, value in rules:
        if pattern.lower() in name.lower():
            axis = value
    return axis


def _defaults(add_options, *argv: str) -> argparse.Namespace:
    """A command's options at their defaults (its own parser's, so they stay the same)."""
    parser = argparse.ArgumentParser(add_help=False)
    add_options(parser)
    return parser.parse_args(list(argv))


def render_options(sweep: Sweep) -> argparse.Namespace:
    """``isolume render``'s options at their defaults, with this sweep's size, view,
    paths, spread, workers and GL."""
    from isolume.app.options import add_render_options

    ns = _defaults(add_render_options)
    ns.size, ns.view, ns.samples = f"{sweep.size[0]}x{sweep.size[1]}", sweep.view_text, sweep.paths
    ns.workers, ns.gl, ns.spread = sweep.workers, sweep.gl, sweep.render_spread
    return ns


def bake_options(sweep: Sweep, iso_range: tuple[float, float]) -> argparse.Namespace:
    """``isolume bake``'s defaults for `iso_range`, with the sweep's paths, target, texel
    error, scale and workers."""
    from isolume.app.options import add_bake_options

    ns = _defaults(add_bake_options, "--out", "unused.npz")
    ns.iso_range, ns.workers = list(iso_range), sweep.workers
    ns.samples, ns.target_error, ns.texel_error, ns.scale = (
        sweep.paths, sweep.target_error, sweep.texel_error, sweep.scale)
    return ns


# -- the volumes -----------------------------------------------------------------------------
def default_folder(data: str | None) -> Path:
    """The ``volumes/`` folder of the data folder (`app.bench.view.data_folder`); when no
    option names one and the current folder has no ``../shared/data``, the one beside the
    repository.

    Raises:
        CLIError: the named folder, or every default, lacks ``volumes/`` (one line).
    """
    from isolume.app.bench.view import DATA_ENV, DEFAULT_DATA, data_folder
    from isolume.app.options import CLIError

    folder, named_by = data_folder(data)
    if (folder / "volumes").is_dir():
        return folder / "volumes"
    if named_by is not None:
        raise CLIError(f"{named_by} {folder}: no volumes/ folder in it; name the data folder "
                       "that holds volumes/, or give VOLUME|FOLDER")
    beside = Path(__file__).resolve().parents[3] / "shared" / "data" / "volumes"
    if beside.is_dir():
        return beside
    raise CLIError(f"no volumes to measure: no {DEFAULT_DATA / 'volumes'} here or beside the "
                   f"repository; give VOLUME|FOLDER, --data DIR or ${DATA_ENV}")


def volume_files(folder: Path) -> list[Path]:
    """The volume files directly in `folder` (by `VOLUME_SUFFIXES`), sorted by name."""
    found = [p for p in folder.iterdir()
             if p.is_file() and p.name.lower().endswith(VOLUME_SUFFIXES)]
    return sorted(found, key=lambda p: p.name.lower())


def volume_specs(named: list[str], data: str | None) -> list[str]:
    """What to measure: each of `named` (a folder holding volume files stands for them; a
    missing path is kept, to fail with its own line), else the default folder's files.

    Raises:
        CLIError: the default folder is missing or holds no volume file.
    """
    from isolume.app.options import CLIError

    if not named:
        folder = default_folder(data)
        files = volume_files(folder)
        if not files:
            raise CLIError(f"{folder}: holds no volume files ({', '.join(VOLUME_SUFFIXES)})")
        return [str(p) for p in files]
    specs = []
    for text in named:
        path = Path(text).expanduser()
        inside = volume_files(path) if not text.startswith("synthetic:") and path.is_dir() else []
        specs += [str(p) for p in inside] or [text]
    return specs


def selected(spec: str, only: str | None) -> bool:
    """True when `only` is None or one of its comma-separated names occurs in the file
    name of `spec` (case-insensitive)."""
    if not only:
        return True
    name = spec if spec.startswith("synthetic:") else Path(spec).name
    return any(part.strip().lower() in name.lower() for part in only.split(",") if part.strip())


@dataclass
class Prepared:
    """A volume ready to measure.

    Attributes:
        volume: as measured (turned, block-meaned); name, source: for the rows.
        isovalues: those measured; suggested: all that ``isolume info`` suggests.
        notes: JSON-ready: dims as loaded and measured (x, y, z), block factor, up axis,
            placement.
        baked: the volume's one bake with ``--bake-range default`` (`case_bake`), once
            its first case has made it.
    """

    volume: Volume
    name: str
    source: str
    isovalues: tuple[float, ...]
    suggested: tuple[float, ...]
    notes: dict[str, Any] = field(default_factory=dict)
    baked: Baked | None = None


def block_factor(shape_xyz: tuple[int, int, int], max_size: int) -> int:
    """Block edge F (voxels) that brings the largest dimension to at most `max_size`,
    leaving at least 2 samples along every axis (1: none; `max_size` 0: none)."""
    if max_size <= 0:
        return 1
    return max(1, min(math.ceil(max(shape_xyz) / max_size), min(shape_xyz) // 2))


def prepare(spec: str, sweep: Sweep) -> Prepared:
    """Load `spec`, turn it by the ``--up`` rules, suggest its isovalues, block-mean it.

    Raises:
        IsolumeError: unreadable volume, or no isovalue to suggest.
    """
    from isolume import volumes

    volume = volumes.load(spec)
    name, source = volume.name, volume.source or spec
    axis = up_axis(Path(spec).name if not spec.startswith("synthetic:") else spec, sweep.up)
    if axis is not None:
        volume = volumes.turn_up(volume, axis)
    suggested = volumes.suggest_isovalues(volume)
    if not suggested:
        raise AccuracyError(f"{source}: no isovalue can be suggested (value range "
                            f"{volume.value_range[0]:g} .. {volume.value_range[1]:g})")
    notes = {"dims_loaded": list(volume.shape_xyz), "up": axis,
             "placement": volume.placement or None}
    factor = block_factor(volume.shape_xyz, sweep.max_size)
    if factor > 1:
        volume = volumes.crop_downsample(volume, None, factor)
    notes.update(block=factor, dims=list(volume.shape_xyz))
    isovalues = suggested[:1] if sweep.first_only else suggested
    if sweep.across:
        from isolume.baking.plan import default_iso_range

        lo, hi = default_iso_range(volume)
        isovalues = tuple(lo + (k + 0.5) * (hi - lo) / sweep.across
                          for k in range(sweep.across))
    return Prepared(volume, name, source, tuple(isovalues), tuple(suggested), notes)


# -- the pictures ----------------------------------------------------------------------------
@dataclass
class Shot:
    """One picture to measure.

    Attributes:
        mode: "render" or "bake"; linear: (N, 3) float64 linear radiance (0 off its
        surface), flat in pixels from the top-left; mask: (N,) its surface pixels;
        render_seconds, bake_seconds: wall times (the bake's None for "render");
        extra: JSON-ready facts (paths per texel, triangles, iso range, texels, levels).
    """

    mode: str
    linear: np.ndarray
    mask: np.ndarray
    render_seconds: float
    bake_seconds: float | None
    extra: dict[str, Any]


def _settings(ns: argparse.Namespace, size: tuple[int, int], shading: str, albedo):
    """`RenderSettings` as ``isolume render`` makes them from its options `ns`."""
    from isolume.app.options import floats
    from isolume.app.render.settings import RenderSettings

    return RenderSettings(size=size, shading=shading, exposure=ns.exposure,
                          auto_exposure=not ns.no_auto_exposure, tonemap=ns.tonemap,
                          albedo=albedo,
                          env_rotation=floats(ns.env_rotation, 2, "--env-rotation"))


def render_default(volume: Volume, iso: float, sweep: Sweep) -> tuple[Shot, BakeConfig]:
    """(`Shot`, its light's `BakeConfig`): the picture ``isolume render`` draws."""
    from isolume.app.options import parse_albedo, view_light
    from isolume.app.render.offscreen import render_volume
    from isolume.baking.config import DEFAULT_ALBEDO

    ns = render_options(sweep)
    config = view_light(ns, volume)
    settings = _settings(ns, sweep.size, "irradiance", parse_albedo(str(DEFAULT_ALBEDO)))
    began = time.perf_counter()
    frame, mesh = render_volume(volume, iso, settings, view=sweep.view, backend=sweep.gl,
                                normals=ns.normals, flip_normals=ns.flip_normals,
                                view_light=config, view_spread=ns.spread,
                                shadows=ns.shadows, workers=sweep.workers,
                                progress=sweep.progress)
    seconds = time.perf_counter() - began
    extra = {"paths_per_texel": config.samples, "spread": sweep.render_spread,
             "triangles": len(mesh.faces)}
    return Shot("render", *_flat(frame), seconds, None, extra), config


@dataclass
class Baked:
    """A lattice a sweep baked, what it cost, and how many cases it draws (`shared_by`:
    their rows carry its paths, seconds and bytes, and sums divide them by it)."""

    lattice: Any
    seconds: float
    bytes: int
    shared_by: int = 1


def bake_cases(volume: Volume, iso_range: tuple[float, float], sweep: Sweep,
               shared_by: int = 1) -> Baked:
    """A bake with ``isolume bake``'s defaults (and the sweep's paths, target, texel error,
    scale) over `iso_range`, timed, its file's bytes measured."""
    from isolume.app.options import bake_config
    from isolume.baking import bake

    config = bake_config(bake_options(sweep, iso_range))
    began = time.perf_counter()
    lattice = bake(volume, config, workers=sweep.workers, progress=sweep.progress)
    seconds = time.perf_counter() - began
    return Baked(lattice, seconds, lattice_bytes(lattice), shared_by)


def case_bake(prep: Prepared, iso: float, sweep: Sweep) -> Baked:
    """The bake the case at `iso` is drawn with: its own over the viewer's range around it
    (``--bake-range view``), or the volume's one over ``isolume bake``'s default range,
    made at its first case and kept in `prep` (``default``)."""
    from isolume.baking.lazy import view_iso_range
    from isolume.baking.plan import default_iso_range

    if sweep.bake_range == "view":
        return bake_cases(prep.volume, view_iso_range(prep.volume, iso), sweep)
    if prep.baked is None:
        prep.baked = bake_cases(prep.volume, default_iso_range(prep.volume), sweep,
                                len(prep.isovalues))
    return prep.baked


def render_baked(volume: Volume, iso: float, sweep: Sweep, baked: Baked) -> Shot:
    """The picture at `iso` drawn with the lattice of `baked` (see the module docstring)."""
    from isolume.app.render.offscreen import render_volume

    lattice, config = baked.lattice, baked.lattice.config
    ns = render_options(sweep)
    settings = _settings(ns, sweep.size, lattice.kind, config.albedo)
    began = time.perf_counter()
    frame, _ = render_volume(volume, iso, settings, view=sweep.view, backend=sweep.gl,
                             normals=ns.normals, flip_normals=ns.flip_normals,
                             lattice=lattice, shadows=ns.shadows, workers=sweep.workers)
    plan = lattice.meta["plan"]
    extra = {"paths": lattice.meta["stats"]["paths"],
             "paths_per_texel": lattice.meta["stats"]["paths"] / max(plan["active_texels"], 1),
             "samples": config.samples, "target_error": config.target_error,
             "texel_error": config.texel_error, "scale": config.scale,
             "lattice_bytes": baked.bytes, "shared_by": baked.shared_by,
             "filled_texels": lattice.meta.get("filled", {}).get("filled", 0),
             "iso_range": list(config.iso_range), "active_texels": plan["active_texels"],
             "levels": len(plan["levels"])}
    return Shot("bake", *_flat(frame), time.perf_counter() - began, baked.seconds, extra)


def lattice_bytes(lattice) -> int:
    """The bytes of `lattice`'s file (`Lattice.save`, written to a temporary folder)."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="isolume-accuracy-") as folder:
        path = Path(folder) / "lattice.npz"
        lattice.save(path)
        return path.stat().st_size


def _flat(frame) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 linear radiance and (N,) mask of a `Frame`."""
    return frame.linear.reshape(-1, 3).astype(np.float64), frame.mask.reshape(-1)


# -- a case ----------------------------------------------------------------------------------
def measure(prep: Prepared, iso: float, sweep: Sweep
            ) -> tuple[list[dict[str, Any]], list[Tile]]:
    """The rows (one per mode) and contact-sheet tiles of `prep` at `iso`."""
    from isolume import volumes

    iso = volumes.check_isovalue(prep.volume, iso)
    shot, config = render_default(prep.volume, iso, sweep)
    if not sweep.skip_bake:
        shots = [shot, render_baked(prep.volume, iso, sweep, case_bake(prep, iso, sweep))]
    else:
        shots = [shot]
    truth = settle_reference(prep.volume, iso, shots, config, sweep)
    rows = [case_row(prep, iso, s, truth) for s in shots]
    return rows, [case_tile(row, s, truth, sweep.size) for row, s in zip(rows, shots,
                                                                         strict=True)]


def case_row(prep: Prepared, iso: float, shot: Shot, truth: Truth) -> dict[str, Any]:
    """The JSON row of one picture (`accuracy_metrics.case_figures` and the times)."""
    from isolume.app.bench.accuracy_metrics import case_figures

    figures = case_figures(shot.linear, shot.mask, truth.radiance, truth.mask, truth.noise)
    return {"volume": prep.name, "source": prep.source, "iso": float(iso), "mode": shot.mode,
            **figures, "render_seconds": shot.render_seconds,
            "bake_seconds": shot.bake_seconds, "reference_seconds": truth.seconds,
            "reference_spp": truth.spp, "reference_kept": truth.kept, **shot.extra}


def case_tile(row: dict[str, Any], shot: Shot, truth: Truth, size: tuple[int, int]) -> Tile:
    """The contact-sheet row of one picture: it and the reference at the reference's
    automatic exposure, and the signed error map."""
    from isolume.app.bench.accuracy_output import Tile, display, error_map
    from isolume.app.render.exposure import auto_exposure_scale

    scale = auto_exposure_scale(truth.radiance, truth.mask)
    label = [row["volume"][:30], f"iso {row['iso']:.5g}, {row['mode']}",
             f"rel RMSE {row['rel_rmse']:.1%} ({row['rel_rmse_less_noise']:.1%})",
             f"ratio {row['mean_ratio']:.3f}, black {row['black_fraction']:.2%}",
             f"ref {row['reference_spp']} spp, noise {row['reference_noise']:.1%}"]
    return Tile(label, display(shot.linear, shot.mask, size, scale),
                display(truth.radiance, truth.mask, size, scale),
                error_map(shot.linear, truth.radiance, truth.mask, size))


# -- the command -----------------------------------------------------------------------------
def _settings_record(sweep: Sweep, specs: list[str]) -> dict:
    """The settings block of accuracy.json."""
    from isolume.app.bench.accuracy_metrics import NOISE_RATIO
    from isolume.app.render.view_gi import DEFAULT_PATHS

    render, bake_ns = render_options(sweep), bake_options(sweep, (0.0, 1.0))
    return {
        "volumes": specs, "size": list(sweep.size), "view": sweep.view_text,
        "max_size": sweep.max_size, "downsampling": "block means of F^3 voxels",
        "isovalues": ("first" if sweep.first_only else f"{sweep.across} across the default "
                      "bake range" if sweep.across else "all suggested"),
        "up": [list(rule) for rule in sweep.up], "gl": sweep.gl, "workers": sweep.workers,
        "render": {"paths": render.samples or f"default ({DEFAULT_PATHS})",
                   "spread": sweep.render_spread, "bounces": render.bounces,
                   "env": "render's default", "seed": render.seed},
        "bake": None if sweep.skip_bake else {
            "samples": bake_ns.samples, "target_error": bake_ns.target_error,
            "texel_error": bake_ns.texel_error, "bounces": bake_ns.bounces, "env": bake_ns.env,
            "scale": bake_ns.scale, "max_levels": bake_ns.max_levels,
            "iso_range": ("baking.lazy.view_iso_range: ±3 % of the data range around iso, "
                          "a bake per case" if sweep.bake_range == "view" else
                          "baking.plan.default_iso_range: one bake per volume")},
        "reference": {"start_spp": START_SPP, "max_spp": sweep.ref_spp,
                      "seed": "the render's + 1",
                      "rule": f"noise <= {NOISE_RATIO:g} x the smallest error less the noise"},
        "metrics": "app.bench.accuracy_metrics (over the reference's surface pixels, RGB)",
    }


def run(args: argparse.Namespace) -> int:
    """Measure every case; print the table and the summary; write the files. Returns 0,
    or 1 when a volume or case failed.

    Raises:
        CLIError: bad options, no volumes to measure, or an unwritable --out.
    """
    from isolume.app.bench.accuracy_output import summary_lines, table_header
    from isolume.app.options import CLIError

    sweep = sweep_of(args)
    every = volume_specs(args.volumes, args.data)
    specs = [s for s in every if selected(s, args.only)]
    if not specs:
        raise CLIError(f"--only {args.only}: matches none of the {len(every)} volumes")
    out = output_folder(Path(args.out).expanduser())
    report = Report(out, _settings_record(sweep, specs))
    report.say(table_header())
    try:
        for number, spec in enumerate(specs, 1):
            _measure_volume(spec, f"[{number}/{len(specs)}]", sweep, report)
            report.save()
    except KeyboardInterrupt:
        report.save(final=True)
        raise
    summary = report.save(final=True)
    print()
    for line in summary_lines(summary):
        print(line)
    print(f"wrote {out / 'accuracy.json'}, {out / 'table.txt'}, {out / 'accuracy.png'} "
          f"({len(report.rows)} cases in {time.perf_counter() - report.began:.0f} s)")
    return 1 if report.failures else 0


def _measure_volume(spec: str, counter: str, sweep: Sweep, report: Report) -> None:
    """Every case of one volume into `report`; bad input and failed cases are recorded
    and skipped."""
    try:
        prep = prepare(spec, sweep)
    except IsolumeError as exc:
        report.fail(spec, None, exc)
        return
    n = prep.notes
    reduced = (f" -> {'x'.join(map(str, n['dims']))} (block means of {n['block']})"
               if n["block"] > 1 else "")
    print(f"{counter} {prep.name}: {'x'.join(map(str, n['dims_loaded']))}{reduced}, "
          f"isovalues {', '.join(f'{v:.6g}' for v in prep.isovalues)}", file=sys.stderr,
          flush=True)
    for iso in prep.isovalues:
        try:
            rows, tiles = measure(prep, iso, sweep)
        except Exception as exc:  # a sweep reports a failed case and goes on
            report.fail(prep.name, iso, exc)
            continue
        for row in rows:
            row["volume_notes"] = n
        report.add(rows, tiles)
