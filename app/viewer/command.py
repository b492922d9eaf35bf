"""The command line of ``isolume view``: its help line, its arguments, and their checked
form (`Options`), everything checked before a window opens. `app.viewer.window.run` runs
the command.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from isolume.app.render.camera import Camera
from isolume.app.state import VolumeSource, add_state_argument

if TYPE_CHECKING:
    import argparse

    from isolume.app.viewer.script import Command

HELP = "open the interactive viewer (live isovalue, light, lazy global illumination)"

DEFAULT_BAKE_SAMPLES = 256
"""Paths per texel a new lazy lattice is refined up to (rounds of 4, 16, 64, 256)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``isolume view``."""
    from isolume.app.options import add_timeline_option, add_volume_options
    from isolume.baking.config import DEFAULT_ENV

    add_volume_options(parser, optional=True)
    parser.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    parser.add_argument("--lattice", metavar="FILE",
                        help="illumination lattice: shown and, if incomplete, baked further "
                        "lazily; a new file is created; saved on exit and with S")
    parser.add_argument("--shading", default=None,
                        help="initial shading mode (default: irradiance when a lattice is "
                        "shown or baked, else phong_hemi)")
    parser.add_argument("--size", default="1024x768", help="window size WxH (screen units)")
    parser.add_argument("--exposure", type=float, default=1.0,
                        help="linear exposure multiplier on the automatic exposure (which "
                        "brings the log-average of the lit surface's luminance to middle "
                        "grey and adapts smoothly)")
    parser.add_argument("--no-auto-exposure", action="store_true",
                        help="no automatic exposure: --exposure is the whole linear scale")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="render N frames once the surface is ready (after --script), "
                        "then exit")
    parser.add_argument("--screenshot", metavar="FILE",
                        help="on exit write FILE.png (sRGB) and FILE.exr (linear radiance)")
    parser.add_argument("--script", metavar="FILE",
                        help="commands, one per line: iso V | orbit DAZ DEL | zoom F | "
                        "pan DX DY | reset | mode NAME | light AZ EL | light camera | "
                        "exposure X | wait-mesh [T] | wait-gi [T] | wait-bake FRACTION [T] | "
                        "wait-light FRACTION [T] | frames N | sleep S | screenshot FILE | "
                        "window-shot FILE | save-view [FILE] | save-lattice [FILE] | "
                        "check-lattice | quit")
    parser.add_argument("--stats", metavar="FILE.json",
                        help="write frame times, extraction and bake figures on exit")
    add_timeline_option(parser)
    parser.add_argument("--no-bake", action="store_true",
                        help="no lazy global illumination (local shading, or --lattice as is)")
    parser.add_argument("--bake-mode", default="irradiance", choices=["irradiance", "sh"],
                        help="what a new lazy lattice holds: irradiance (fixed light) or SH "
                        "transfer (the environment rotates with the light controls)")
    parser.add_argument("--bake-env", default=DEFAULT_ENV,
                        help="environment of a new lazy lattice: constant:R,G,B | sky[:...] | "
                        f"FILE.exr/.hdr (as isolume bake --env; default {DEFAULT_ENV})")
    parser.add_argument("--bake-samples", type=int, default=DEFAULT_BAKE_SAMPLES,
                        help="paths per texel the lazy bake refines up to (new lattices)")
    parser.add_argument("--bake-workers", type=int, default=None,
                        help="threads of the lazy bake process: its tracing, plan kernels, "
                        "Embree builds and BLAS (default: the cores this process may use)")
    parser.add_argument("--bake-max-levels", type=int, default=64, metavar="K",
                        help="isovalue levels of a new lazy lattice (fewer: the first sweep "
                        "builds fewer scenes and converges sooner, texels move farther "
                        "onto their levels and a few come out wrong; default 64)")
    parser.add_argument("--no-ui", action="store_true", help="no control panel")
    parser.add_argument("--normals", default="smooth", choices=["smooth", "gradient"],
                        help="shading normals: B-spline-smoothed gradient or plain central "
                        "differences (default smooth)")
    parser.add_argument("--flip-normals", action="store_true",
                        help="material less dense than air")
    add_state_argument(parser)


@dataclass(frozen=True)
class Options:
    """Validated viewer options (everything checked before a window opens).

    Attributes:
        size: window size (W, H) in screen units.
        script: the parsed ``--script`` (`app.viewer.script.Command`s).
        screenshot, stats, lattice_path: files written on exit (None: none).
        bake: whether a lazy bake may run; bake_*: the lazy bake's settings.
        ui: whether the control panel is drawn.
        source: the volume as the command line names it (for saved views).
        camera: the camera to start from (``--state``; None: the first surface framed).
        light: (azimuth, elevation) degrees of a world-fixed light to start with
            (``--state``; None: the light follows the camera).
    """

    size: tuple[int, int]
    shading: str | None
    exposure: float
    auto_exposure: bool
    frames: int | None
    screenshot: Path | None
    script: tuple[Command, ...]
    stats: Path | None
    bake: bool
    bake_mode: str
    bake_env: str
    bake_samples: int
    bake_workers: int | None
    bake_max_levels: int
    ui: bool
    normals: str
    flip_normals: bool
    lattice_path: Path | None
    source: VolumeSource
    camera: Camera | None
    light: tuple[float, float] | None


def read_options(args: argparse.Namespace) -> Options:
    """Check the command line; raise `app.options.CLIError` with one-line messages."""
    from isolume.app.options import CLIError, check_picture_memory, parse_exposure, parse_size
    from isolume.app.render.images import check_output_path
    from isolume.app.render.settings import SHADING_MODES
    from isolume.app.viewer.script import load_script

    if args.shading is not None and args.shading not in SHADING_MODES:
        raise CLIError(f"--shading {args.shading!r}: expected one of {', '.join(SHADING_MODES)}")
    parse_exposure(args.exposure)
    if args.frames is not None and args.frames < 1:
        raise CLIError(f"--frames {args.frames}: expected at least 1")
    if args.bake_samples < 1:
        raise CLIError(f"--bake-samples {args.bake_samples}: expected at least 1")
    if args.bake_workers is not None and args.bake_workers < 1:
        raise CLIError(f"--bake-workers {args.bake_workers}: expected at least 1")
    if not 2 <= args.bake_max_levels <= 1024:
        raise CLIError(f"--bake-max-levels {args.bake_max_levels}: expected 2 to 1024")
    if not args.no_bake:
        from isolume.baking.environment import parse_env

        parse_env(args.bake_env)  # EnvSpecError (a one-line user error) before any window
    screenshot = check_output_path(args.screenshot) if args.screenshot else None
    stats = check_output_path(args.stats, (".json",)) if args.stats else None
    lattice = check_output_path(args.lattice, (".npz",)) if args.lattice else None
    script = tuple(load_script(args.script, SHADING_MODES)) if args.script else ()
    size = parse_size(args.size)
    check_picture_memory(size, "local")
    return Options(
        size=size, shading=args.shading, exposure=args.exposure,
        auto_exposure=not args.no_auto_exposure,
        frames=args.frames, screenshot=screenshot, script=script, stats=stats,
        bake=not args.no_bake, bake_mode=args.bake_mode, bake_env=args.bake_env,
        bake_samples=args.bake_samples, bake_workers=args.bake_workers,
        bake_max_levels=args.bake_max_levels, ui=not args.no_ui, normals=args.normals,
        flip_normals=args.flip_normals, lattice_path=lattice,
        source=VolumeSource.from_args(args), camera=args.camera, light=args.light_angles,
    )


def script_commands(options: Options) -> list[Command]:
    """The `app.viewer.script.Command`s the viewer runs: ``--script``, then, for
    ``--frames N``, N frames (after the surface, without a script) and quit."""
    from isolume.app.viewer.script import Command

    commands = list(options.script)
    if options.frames is not None:
        if not commands:
            commands.append(Command("wait-mesh", (), 0))
        commands += [Command("frames", (options.frames,), 0), Command("quit", (), 0)]
    return commands
