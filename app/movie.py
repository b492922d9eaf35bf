"""The ``isolume movie`` command: a turntable, a light orbit or an isovalue sweep, rendered
off-screen with one GL context to an MP4 file or a folder of PNG frames.

The frames look as ``isolume render`` draws them with the same options (the same
lattice, shading, lighting and tone curve), all at one exposure: metered once over a few
frames spread over the movie (`app.movie_stage.meter`), or ``--exposure`` alone with
``--no-auto-exposure``. The same arguments give the same frames, byte for byte. The
frames are drawn by `app.movie_stage`, written by `app.movie_output`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from isolume import volumes
from isolume.app import allocator
from isolume.app.look import shading_look
from isolume.app.movie_stage import (
    KINDS,
    Scene,
    Shot,
    Stage,
    light_turn,
    make_shots,
    meter,
    metered_shots,
    turn_steps,
)
from isolume.app.options import (
    CLIError,
    add_render_options,
    add_volume_options,
    check_picture_memory,
    check_served,
    isovalue,
    load_lattice,
    load_volume,
    parse_size,
)
from isolume.app.state import add_state_argument

if TYPE_CHECKING:

    from isolume.app.look import Look
    from isolume.app.movie_stage import LightTurn
    from isolume.app.render.camera import Camera
    from isolume.app.render.settings import RenderSettings
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice

HELP = "render a turntable, light-orbit or isovalue-sweep movie off-screen to MP4 or PNG frames"
DESCRIPTION = """\
Render a movie off-screen with one GL context: a turntable (the camera's azimuth turns
--degrees about the volume), a light orbit (the sun or the environment turns --degrees
about the up axis) or an isovalue sweep (--iso-range, one lattice lighting every
isovalue). Frames look as `isolume render` draws them with the same options, all at one
exposure metered over --meter-frames frames (no flicker); the same arguments give the
same frames."""
EPILOG = """\
examples:
  isolume movie synthetic:torus --out torus.mp4 --frames 48 --size 640x480
  isolume movie engine.raw --lattice engine.npz --kind light --out frames/
  isolume movie synthetic:engine --kind iso --iso-range 0.2 0.6 --out sweep.mp4"""
DEFAULT_FRAMES = 72
DEFAULT_FPS = 24.0
DEFAULT_METER_FRAMES = 4
DEFAULT_CRF = 18
SWEEP_FRACTION = 0.1
"""Without a lattice or --iso-range, a sweep runs this fraction of the data range on either
side of --iso."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume movie``."""
    p.description, p.epilog = DESCRIPTION, EPILOG
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    add_volume_options(p, optional=True)
    p.add_argument("--out", required=True,
                   help="FILE.mp4 (H.264, yuv420p: even width and height) or FOLDER/ for "
                   "PNG frames frame_0000.png, ... (created if missing)")
    p.add_argument("--kind", default="turntable", choices=KINDS,
                   help="what turns or changes: the camera's azimuth (turntable), the "
                   "light's (light) or the isovalue (iso) (default turntable)")
    p.add_argument("--turntable", dest="kind", action="store_const", const="turntable",
                   help="the same as --kind turntable")
    p.add_argument("--sweep", metavar="LO:HI", default=None,
                   help="the same as --kind iso --iso-range LO HI (default: no sweep)")
    p.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                   help=f"frames in the movie (default {DEFAULT_FRAMES})")
    p.add_argument("--fps", type=float, default=DEFAULT_FPS,
                   help=f"frames per second of the MP4 (default {DEFAULT_FPS:g})")
    p.add_argument("--turntable-light", choices=["camera", "world"], default=None,
                   help="--kind turntable: the light turns with the camera, as on a real "
                   "turntable where the object turns under the lamps (camera), or stays put "
                   "while the camera circles (world) (default camera where the picture's "
                   "light can turn, else world, said on stderr)")
    p.add_argument("--degrees", type=float, default=360.0,
                   help="turn over the movie about the up axis, degrees: a whole number of "
                   "turns loops seamlessly (default 360)")
    p.add_argument("--iso-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="isovalues of the sweep, LO in the first frame and HI in the last "
                   "(default: the range the lattice was baked for, else "
                   f"±{SWEEP_FRACTION * 100:.0f}%% of the data range around --iso)")
    p.add_argument("--save-lattice", metavar="FILE.npz", default=None,
                   help="--kind iso without --lattice: keep the lattice baked for the sweep "
                   "(resumed if present; pass it as --lattice next time) (default: not kept)")
    p.add_argument("--meter-frames", type=int, default=DEFAULT_METER_FRAMES, metavar="K",
                   help="meter the movie's one exposure over K frames spread over it "
                   f"(1: the first frame only; default {DEFAULT_METER_FRAMES})")
    p.add_argument("--crf", type=int, default=DEFAULT_CRF,
                   help="MP4 quality: x264's constant rate factor, 0 (lossless) to 51 "
                   f"(default {DEFAULT_CRF})")
    add_render_options(p)
    add_state_argument(p)


@dataclass(frozen=True)
class Request:
    """The checked options of a movie that need no volume.

    Attributes:
        kind: one of `app.movie_stage.KINDS`.
        frames: how many frames.
        fps: frames per second.
        degrees: the turn over the movie, degrees.
        size: (width, height) pixels.
        view: (azimuth, elevation, distance or None) of the first frame.
        out: the MP4 file or the PNG folder.
        folder: whether `out` is a PNG folder.
        crf: the MP4's x264 constant rate factor.
    """

    kind: str
    frames: int
    fps: float
    degrees: float
    size: tuple[int, int]
    view: tuple[float, float, float | None]
    out: Path
    folder: bool
    crf: int


def apply_sweep(args: argparse.Namespace) -> None:
    """``--sweep LO:HI`` as ``--kind iso --iso-range LO HI`` (in `args`)."""
    if args.sweep is None:
        return
    if args.iso_range is not None:
        raise CLIError("--sweep and --iso-range: give one of them")
    try:
        lo, hi = (float(v) for v in args.sweep.split(":"))
    except ValueError:
        raise CLIError(f"--sweep {args.sweep!r}: expected LO:HI, e.g. 0.2:0.6") from None
    args.kind, args.iso_range = "iso", [lo, hi]


def check_request(args: argparse.Namespace) -> Request:
    """The options that need no volume, checked first (`CLIError`, `OutputError`: one line)."""
    apply_sweep(args)
    from isolume.app.movie_output import check_movie_output, is_folder
    from isolume.app.render.camera import parse_view
    from isolume.app.render.images import check_output_path

    if not 1 <= args.frames <= 100_000:
        raise CLIError(f"--frames {args.frames}: expected 1 to 100000")
    if not 0 < args.fps <= 1000:
        raise CLIError(f"--fps {args.fps:g}: expected more than 0 and at most 1000")
    if not math.isfinite(args.degrees):
        raise CLIError(f"--degrees {args.degrees:g}: expected a finite angle")
    if args.meter_frames < 1:
        raise CLIError(f"--meter-frames {args.meter_frames}: expected at least 1")
    if not 0 <= args.crf <= 51:
        raise CLIError(f"--crf {args.crf}: expected 0 (lossless) to 51")
    if args.turntable_light is not None and args.kind != "turntable":
        raise CLIError("--turntable-light: only for --kind turntable")
    if args.iso_range is not None and args.kind != "iso":
        raise CLIError("--iso-range: only for --kind iso (the isovalue sweep)")
    if args.save_lattice is not None and (args.kind != "iso" or args.lattice is not None):
        raise CLIError("--save-lattice: only for --kind iso without --lattice (it keeps the "
                       "lattice baked for the sweep)")
    if args.save_lattice is not None:
        check_output_path(args.save_lattice, (".npz",))
    size = parse_size(args.size)
    check_picture_memory(size, "local")
    try:
        view = parse_view(args.view)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    out = check_movie_output(args.out, size)
    return Request(args.kind, args.frames, args.fps, args.degrees, size, view, out,
                   is_folder(args.out), args.crf)


def sweep_range(args: argparse.Namespace, vol: volumes.Volume,
                lattice: Lattice | HeldLattice | None,
                iso: float) -> tuple[float, float]:
    """(lo, hi) isovalues of a sweep: ``--iso-range``, else the lattice's served range
    (`baking.plan.served_range`), else `SWEEP_FRACTION` of the data range around `iso`;
    each end checked against the data and the lattice."""
    from isolume.baking.plan import served_range

    vmin, vmax = vol.value_range
    half = SWEEP_FRACTION * (vmax - vmin)
    served = served_range(lattice.meta) if lattice is not None else None
    lo, hi = (args.iso_range or served or (max(vmin, iso - half), min(vmax, iso + half)))
    if not lo < hi:
        raise CLIError(f"--iso-range {lo:g} {hi:g}: expected LO < HI")
    for value in (lo, hi):
        volumes.check_isovalue(vol, value)
        check_served(lattice, value, args.lattice)
    return float(lo), float(hi)


def bake_sweep(vol: volumes.Volume, traced: BakeConfig, iso_range: tuple[float, float],
               args: argparse.Namespace) -> Lattice:
    """The lattice for a sweep without ``--lattice``: `traced`'s light baked for the
    isovalues `iso_range` (`baking.bake`, progress on stderr; kept in
    ``--save-lattice``): ``--samples`` paths at every texel, or without it ``isolume
    bake``'s default (`app.options.bake_paths`)."""
    from isolume.app.options import bake_paths
    from isolume.baking import bake

    out = Path(args.save_lattice) if args.save_lattice else None
    samples, _, texel = bake_paths(args.samples, None, None, traced.mode)
    config = replace(traced, iso_range=iso_range, samples=samples, texel_error=texel)
    lo, hi = iso_range
    kept = f", kept in {out}" if out is not None else " (--save-lattice FILE.npz keeps it)"
    paths = (f"to a texel error of {texel:g} at {samples} paths a traced texel" if texel
             else f"with {samples} paths per texel")
    print(f"isolume: no --lattice: baking one for isovalues {lo:g} to {hi:g} {paths}{kept}",
          file=sys.stderr)
    return bake(vol, config, out=out, workers=args.workers, progress=True)


def frame_text(kind: str, shot: Shot, camera: Camera, exposure: float,
               settings: RenderSettings) -> dict[str, str]:
    """The PNG text chunks of a frame: what it shows, from which `camera` (the whole
    camera as a state file's ``camera`` holds it: `app.state`), and the exposure it was
    drawn with (numbers as Python reads them back exactly)."""
    from dataclasses import asdict

    return {"Software": "isolume movie", "kind": kind, "frame": str(shot.index),
            "azimuth": repr(shot.azimuth), "elevation": repr(camera.elevation),
            "camera": json.dumps(asdict(camera)),
            "isovalue": repr(shot.iso), "light turn": repr(shot.turn),
            "exposure": repr(exposure), "shading": settings.shading,
            "tonemap": settings.tonemap}


def movie_exposure(args: argparse.Namespace, stage: Stage, shots: list[Shot]
                   ) -> tuple[float, list[Shot]]:
    """(the movie's linear exposure, the shots metered for it): ``--exposure`` times the
    automatic exposure of `--meter-frames` shots, or ``--exposure`` alone with
    ``--no-auto-exposure`` (no shot metered)."""
    if args.no_auto_exposure:
        return args.exposure, []
    metered = metered_shots(shots, args.meter_frames)
    print(f"metering the exposure on frame{'s' * (len(metered) > 1)} "
          f"{', '.join(str(s.index) for s in metered)}", file=sys.stderr)
    return args.exposure * meter(stage, metered), metered


def write_frames(request: Request, stage: Stage, shots: list[Shot], exposure: float,
                 comment: str) -> None:
    """Draw every shot at `exposure` and write it, a progress bar on stderr; a Ctrl-C
    closes the output with the frames written so far and says how many (an MP4 of none
    is removed)."""
    from tqdm import tqdm

    from isolume.app.movie_output import Mp4Frames, PngFrames

    writer = (PngFrames(request.out, request.frames) if request.folder
              else Mp4Frames(request.out, request.size, request.fps, request.crf, comment))
    written = 0
    try:
        with writer, tqdm(total=len(shots), unit="frame", desc=request.kind,
                          file=sys.stderr, dynamic_ncols=True) as bar:
            for shot in shots:
                frame = stage.draw(shot, exposure)
                writer.write(shot.index, frame.srgb, frame_text(
                    request.kind, shot, stage.scene.camera(shot), exposure,
                    stage.scene.settings))
                written += 1
                bar.update()
    except KeyboardInterrupt:
        _say_stopped(request, written, len(shots))
        raise
    others = writer.others() if request.folder else []
    if others:
        print(f"isolume: warning: {request.out} also holds {len(others)} other frame_*.png "
              "files (not of this movie)", file=sys.stderr)


def _say_stopped(request: Request, written: int, frames: int) -> None:
    """Say on stderr what a movie stopped after `written` of its `frames` left in its
    output; an MP4 of no frame is removed."""
    if written == 0 and not request.folder:
        request.out.unlink(missing_ok=True)
        print(f"isolume: stopped before the first frame; {request.out} was not kept",
              file=sys.stderr)
    else:
        print(f"isolume: stopped after {written} of {frames} frames; {request.out} holds "
              "them", file=sys.stderr)


def movie_camera(volume: volumes.Volume, request: Request, iso: float,
                 iso_range: tuple[float, float] | None) -> Camera:
    """The camera of the first frame at ``--view`` (`request.view`) that frames the surface
    of every frame (the sweep's `iso_range`, else `iso`) from every azimuth the movie
    turns to (`app.render.renderer.framed_camera`), so that nothing zooms."""
    from isolume.app.render.renderer import framed_camera

    az = request.view[0]
    azimuths = (tuple(az + t for t in turn_steps(request.frames, request.degrees))
                if request.kind == "turntable" else ())
    lo, hi = iso_range if iso_range is not None else (iso, None)
    return framed_camera(volume, lo, request.view, request.size, iso_hi=hi, azimuths=azimuths)


def run(args: argparse.Namespace) -> int:
    """Render the movie; returns the exit status."""
    request = check_request(args)
    vol = load_volume(args)
    lattice = load_lattice(args.lattice, vol, args.env)
    look = shading_look(args, vol, lattice, request.size, per="frame")
    iso = isovalue(vol, args.iso)
    iso_range = sweep_range(args, vol, lattice, iso) if request.kind == "iso" else None
    if iso_range is None:
        check_served(lattice, iso, args.lattice)
    traced = look.traced
    if iso_range is not None and traced is not None:
        lattice, traced = bake_sweep(vol, traced, iso_range, args), None
    allocator.for_pictures()
    az = request.view[0]
    camera = args.camera or movie_camera(vol, request, iso, iso_range)
    scene = Scene(vol, look.settings, camera, normals=args.normals,
                  flip_normals=args.flip_normals, lattice=lattice, env_coeffs=look.env_coeffs,
                  traced=traced, spread=args.spread, shadows=args.shadows,
                  workers=args.workers)
    first = scene.camera(Shot(0, az, iso))
    follows = False
    if request.kind == "light":
        scene = replace(scene, light=light_turn(look.settings.shading, lattice, traced, first,
                                                look.settings, args.lattice))
    elif request.kind == "turntable" and args.turntable_light != "world":
        turn = turntable_light(args, look, lattice, traced, first)
        follows = turn is not None
        scene = replace(scene, light=turn)
    report_light(scene, args.lattice)
    shots = make_shots(request.kind, request.frames, az, iso, request.degrees, iso_range,
                       light_follows=follows)
    t0 = time.perf_counter()
    with Stage(scene, args.gl) as stage:
        exposure, metered = movie_exposure(args, stage, shots)
        write_frames(request, stage, shots, exposure, movie_comment(request, vol, exposure))
        empty = len(stage.empty_isos)
    seconds = time.perf_counter() - t0
    if empty:
        print(f"isolume: warning: {empty} isovalue(s) show no surface", file=sys.stderr)
    print(summary(request, vol, scene, shots, exposure, metered, seconds))
    return 0


def turntable_light(args: argparse.Namespace, look: Look, lattice: Lattice | HeldLattice | None,
                    traced: BakeConfig | None, first: Camera) -> LightTurn | None:
    """How a turntable's light turns with its camera (`app.movie_stage.LightTurn`), or None
    where it cannot and ``--turntable-light`` did not ask for it (said on stderr).

    Raises:
        CLIError: ``--turntable-light camera`` asked for a turn the light cannot make.
    """
    try:
        return light_turn(look.settings.shading, lattice, traced, first, look.settings,
                          args.lattice, asked="--turntable-light camera")
    except CLIError as exc:
        if args.turntable_light == "camera":
            raise
        print(f"isolume: the light stays put while the camera circles ({exc})",
              file=sys.stderr)
        return None


def report_light(scene: Scene, source: str | None) -> None:
    """Say on stderr how the frames' light is had when it costs or leaves something out:
    traced for every frame, or a lattice's sun turned per pixel over its baked bounces."""
    if scene.traced is not None:
        print(f"isolume: no --lattice: global illumination is traced for every frame "
              f"({scene.traced.samples} paths a texel on average)", file=sys.stderr)
    if scene.light is not None and scene.light.how == "pixels":
        print(f"isolume: note: the light turns per pixel; the bounces {source} holds stay "
              "as baked for its direction (without --lattice each frame's light is traced)",
              file=sys.stderr)


def movie_comment(request: Request, vol: volumes.Volume, exposure: float) -> str:
    """The MP4's comment: the command's kind, the volume and the fixed exposure."""
    return (f"isolume movie --kind {request.kind} {vol.source or vol.name}, "
            f"exposure {exposure!r}")


def summary(request: Request, vol: volumes.Volume, scene: Scene, shots: list[Shot],
            exposure: float, metered: list[Shot], seconds: float) -> str:
    """The line ``isolume movie`` prints when done."""
    w, h = request.size
    first, last = shots[0], shots[-1]
    what = {"turntable": f"turntable {request.degrees:g}° from azimuth {first.azimuth:g}",
            "light": f"light orbit {request.degrees:g}°",
            "iso": f"isovalues {first.iso:.6g} to {last.iso:.6g}"}[request.kind]
    iso = "" if request.kind == "iso" else f" at iso {first.iso:.6g}"
    how = (f"metered over frame{'s' * (len(metered) > 1)} "
           f"{', '.join(str(s.index) for s in metered)}" if metered else "as given")
    return (f"wrote {request.out} ({len(shots)} frames {w}x{h} at {request.fps:g} fps, {what}, "
            f"{vol.name}{iso}, shading {scene.settings.shading}, exposure {exposure:.6g} "
            f"fixed, {how}) in {seconds:.1f} s ({seconds / len(shots):.2f} s per frame)")
