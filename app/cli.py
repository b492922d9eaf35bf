"""The ``isolume`` command line (DESIGN §6).

Every user error (bad file, bad value, missing GL) ends in a one-line message on stderr
and exit status 2; no tracebacks. Heavy modules are imported inside the commands so that
``isolume info`` and ``isolume bake`` never load OpenGL.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

import numpy as np

import volumes

EXIT_USER_ERROR = 2


class CLIError(ValueError):
    """A bad command-line value; the message says what was expected."""


def _user_errors() -> tuple[type[BaseException], ...]:
    """Exception types that mean bad input (reported in one line), not a bug."""
    errors: list[type[BaseException]] = [CLIError, volumes.VolumeError]
    from .images import OutputError

    errors.append(OutputError)
    try:
        from .render import RenderError

        errors.append(RenderError)
    except ImportError:
        pass
    try:
        from .glcontext import GLUnavailable

        errors.append(GLUnavailable)
    except ImportError:  # moderngl missing: render commands report it themselves
        pass
    try:
        from baking.errors import BakeError

        errors.append(BakeError)
    except ImportError:
        pass
    try:
        from baking.environment import EnvSpecError

        errors.append(EnvSpecError)
    except ImportError:
        pass
    return tuple(errors)


# -- argument helpers -------------------------------------------------------------------
def _floats(text: str, count: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise CLIError(f"{what} {text!r}: expected {count} comma-separated numbers") from None
    if len(values) != count or not np.isfinite(values).all():
        raise CLIError(f"{what} {text!r}: expected {count} comma-separated finite numbers")
    return values


def _size(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise CLIError(f"--size {text!r}: expected WxH, e.g. 512x512") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise CLIError(f"--size {text!r}: width and height must be between 1 and 16384")
    return w, h


def _load_volume(args: argparse.Namespace) -> volumes.Volume:
    options = {}
    if getattr(args, "dims", None):
        options["dims"] = tuple(int(v) for v in _floats(args.dims, 3, "--dims"))
    if getattr(args, "dtype", None):
        options["dtype"] = args.dtype
    if getattr(args, "spacing", None):
        options["spacing"] = _floats(args.spacing, 3, "--spacing")
    volume = volumes.load(args.volume, **options)
    if getattr(args, "up", None):
        volume = volumes.turn_up(volume, args.up)
    return volume


def _isovalue(volume: volumes.Volume, iso: float | None) -> float:
    """The requested isovalue, or the first suggested one."""
    if iso is None:
        suggested = volumes.suggest_isovalues(volume)
        if not suggested:
            raise CLIError(
                f"{volume.source or volume.name}: no isovalue given and none can be suggested "
                f"(value range {volume.value_range}); pass --iso"
            )
        return suggested[0]
    return volumes.check_isovalue(volume, iso)


def _load_lattice(path: str | None, volume: volumes.Volume):
    """The lattice at `path` checked against `volume`, or None."""
    if path is None:
        return None
    from baking.lattice import Lattice

    return Lattice.load(path, volume)


def _environment_coefficients(spec: str | None, lattice, window: str):
    """(n², 3) SH coefficients of the display environment for an SH lattice."""
    from baking import sh
    from baking.environment import parse_env

    spec = spec or lattice.meta["config"].get("env") or "constant:1,1,1"
    order = int(lattice.meta["sh_order"])
    try:  # a split transfer (sun per pixel) also takes the sky without its sun
        return sh.display_coefficients(parse_env(spec), order, sh.transfer_blocks(lattice.meta),
                                       window=None if window == "none" else window)
    except ValueError as exc:
        raise CLIError(f"--env {spec}: {exc}") from None


def _add_volume_options(p: argparse.ArgumentParser, optional: bool) -> None:
    p.add_argument(
        "volume", nargs="?" if optional else None, default=None,
        help="volume file or synthetic:NAME[:SIZE]"
        + (f" (default {volumes.DEFAULT})" if optional else ""),
    )
    p.add_argument("--dims", help="X,Y,Z for raw files whose name does not say")
    p.add_argument("--dtype", help="sample type for raw files, e.g. uint8, int16, float32")
    p.add_argument("--spacing", help="voxel size X,Y,Z (overrides the file)")
    p.add_argument("--up", metavar="AXIS", default=None,
                   help="the volume's axis that points up: x, y, z, -x, -y or -z (after the "
                   "orientation its header gives; e.g. -z for raw slices that run top "
                   "to bottom; default z)")


def _add_render_options(p: argparse.ArgumentParser) -> None:
    from baking.config import DEFAULT_ENV

    from .render import SHADING_MODES, TONEMAPS

    p.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    p.add_argument("--shading", default=None,
                   help=f"one of {', '.join(SHADING_MODES)} (default: the lattice's kind "
                   "with --lattice, else irradiance: global illumination traced for this "
                   "view)")
    p.add_argument("--lattice", help="illumination lattice from `isolume bake`")
    p.add_argument("--env", default=None,
                   help="the lighting: constant:R,G,B | sky[:k=v,...] | "
                   "FILE.exr/.hdr[@angular] (default: the lattice's with --lattice, else "
                   f"{DEFAULT_ENV})")
    p.add_argument("--light", action="append", metavar="SPEC",
                   help="point:X,Y,Z:R,G,B or dir:X,Y,Z:R,G,B (repeatable; without --lattice)")
    p.add_argument("--samples", type=int, default=None,
                   help="paths per texel of the global illumination traced for this view "
                   "(without --lattice; default 64)")
    p.add_argument("--bounces", type=int, default=2,
                   help="diffuse bounces of that illumination (default 2)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--workers", type=int, default=None,
                   help="tracing threads (default: all cores)")
    p.add_argument("--env-rotation", default="0,0", help="AZ,EL degrees (--shading sh)")
    p.add_argument("--sh-window", default="none", choices=["none", "hanning", "lanczos"],
                   help="window against ringing of the environment's SH projection")
    p.add_argument("--size", default="512x512", help="WxH pixels")
    p.add_argument("--view", default="30,30", help="AZ,EL[,DIST]: degrees, diagonals")
    p.add_argument("--exposure", type=float, default=1.0,
                   help="linear exposure multiplier on the automatic exposure (which brings "
                   "the log-average of the surface's luminance to middle grey)")
    p.add_argument("--no-auto-exposure", action="store_true",
                   help="no automatic exposure: --exposure is the whole linear scale")
    p.add_argument("--tonemap", default="aces", choices=list(TONEMAPS))
    p.add_argument("--albedo", default=None,
                   help="A or R,G,B diffuse reflectance (default: the lattice's, else 0.8)")
    p.add_argument("--normals", default="smooth", choices=["smooth", "gradient"])
    p.add_argument("--flip-normals", action="store_true", help="material less dense than air")
    p.add_argument("--gl", default="auto", choices=["auto", "egl", "osmesa"])


def parse_albedo(text: str) -> tuple[float, float, float]:
    """``A`` or ``R,G,B`` in [0, 1] → RGB tuple."""
    parts = text.split(",")
    values = _floats(text, len(parts), "--albedo") if len(parts) in (1, 3) else None
    if values is None:
        raise CLIError(f"--albedo {text!r}: expected A or R,G,B")
    if len(values) == 1:
        values = values * 3
    if min(values) < 0 or max(values) > 1:
        raise CLIError(f"--albedo {text!r}: reflectance must lie in [0, 1]")
    return values


# -- commands ---------------------------------------------------------------------------
def cmd_info(args: argparse.Namespace) -> int:
    """Print dimensions, spacing, value range, histogram and suggested isovalues."""
    vol = _load_volume(args)
    z, y, x = vol.data.shape
    lo, hi = vol.value_range
    print(f"volume     {vol.source or vol.name}")
    print(f"dims       {x} x {y} x {z} (X x Y x Z), {vol.data.size:,} voxels")
    print(f"spacing    {', '.join(f'{s:g}' for s in vol.spacing)}")
    print(f"origin     {', '.join(f'{s:g}' for s in vol.origin)}")
    if vol.placement:
        print(f"placement  {vol.placement}")
    print(f"range      {lo:g} .. {hi:g}")
    print("histogram (log counts)")
    for line in volumes.histogram_lines(vol):
        print("  " + line)
    suggested = volumes.suggest_isovalues(vol)
    if suggested:
        print(f"suggested isovalues: {', '.join(f'{s:.6g}' for s in suggested)}")
    else:
        print("suggested isovalues: none (constant volume)")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    """Render the isosurface off-screen to PNG (sRGB) or EXR (linear radiance)."""
    from .camera import parse_view
    from .images import check_output_path, write_image
    from .offscreen import render_volume
    from .render import LATTICE_MODES, RenderSettings

    out = check_output_path(args.out)
    vol = _load_volume(args)
    lattice = _load_lattice(args.lattice, vol)
    shading = args.shading or (lattice.kind if lattice is not None else "irradiance")
    if lattice is not None and lattice.kind == "irradiance" and (args.env or args.light):
        raise CLIError(f"--env/--light: {args.lattice} holds irradiance baked under its own "
                       f"lighting ({lattice.meta['config'].get('env') or 'no environment'}); "
                       "bake again for other light, or leave out --lattice")
    view_light = _view_light(args, vol) if lattice is None and shading == "irradiance" else None
    if args.albedo is not None:
        albedo = parse_albedo(args.albedo)
    elif lattice is not None:
        albedo = tuple(lattice.meta["config"]["albedo"])
    else:
        albedo = (0.8, 0.8, 0.8)
    try:
        view = parse_view(args.view)
        settings = RenderSettings(
            size=_size(args.size), shading=shading, exposure=args.exposure,
            auto_exposure=not args.no_auto_exposure, tonemap=args.tonemap, albedo=albedo,
            env_rotation=_floats(args.env_rotation, 2, "--env-rotation"),
        )
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    env_coeffs = None
    if shading == "sh" and lattice is not None:
        env_coeffs = _environment_coefficients(args.env, lattice, args.sh_window)
    if shading in LATTICE_MODES and lattice is None and view_light is None:
        raise CLIError(f"--shading {shading} needs --lattice FILE (make one with isolume "
                       "bake); without one, irradiance is traced for the view")
    iso = _isovalue(vol, args.iso)
    if lattice is not None:
        from baking.plan import outside_served_range

        refused = outside_served_range(lattice.meta, iso, args.lattice)
        if refused:
            raise CLIError(refused)
    frame, mesh = render_volume(
        vol, iso, settings, view=view, backend=args.gl,
        normals=args.normals, flip_normals=args.flip_normals, lattice=lattice,
        env_coeffs=env_coeffs, view_light=view_light, workers=args.workers, progress=True,
    )
    if mesh.empty:
        print(f"isolume: warning: {mesh.message}", file=sys.stderr)
    write_image(out, frame.linear, frame.srgb)
    lighting = f", lighting {view_light.env}" if view_light is not None else ""
    print(f"wrote {out} ({settings.size[0]}x{settings.size[1]}, {vol.name} at iso {iso:.6g}, "
          f"{len(mesh.faces):,} triangles, shading {settings.shading}{lighting}, exposure "
          f"{frame.exposure:.3g})")
    return 0


def _view_light(args: argparse.Namespace, volume: volumes.Volume):
    """The `BakeConfig` of the global illumination ``render`` traces for its view (the
    lighting ``reference`` path-traces with the same arguments)."""
    from baking.config import DEFAULT_ENV, BakeConfig

    from .view_gi import DEFAULT_PATHS

    samples = DEFAULT_PATHS if args.samples is None else args.samples
    if not 1 <= samples <= 4096:
        raise CLIError(f"--samples {samples}: expected 1 to 4096 paths per texel")
    if args.workers is not None and args.workers < 1:
        raise CLIError(f"--workers {args.workers}: expected at least 1")
    env = DEFAULT_ENV if args.env is None else args.env
    return BakeConfig(
        mode="irradiance", samples=samples, bounces=args.bounces,
        albedo=parse_albedo(args.albedo or "0.8"), env="" if env == "none" else env,
        lights=tuple(args.light or ()), seed=args.seed, normals=args.normals,
        flip_normals=args.flip_normals,
    )


def _bake_config(args: argparse.Namespace):
    from baking.config import BakeConfig

    return BakeConfig(
        mode=args.mode, sh_order=args.sh_order, samples=args.samples, bounces=args.bounces,
        albedo=parse_albedo(args.albedo), scale=args.scale,
        iso_range=tuple(args.iso_range) if args.iso_range else None,
        env="" if args.env == "none" else args.env, lights=tuple(args.light or ()), seed=args.seed,
        flip_normals=args.flip_normals, target_error=args.target_error,
        max_samples=max(args.max_samples, args.samples), max_levels=args.max_levels,
        max_move=args.max_move, direct_light=args.direct_light,
    )


def cmd_bake(args: argparse.Namespace) -> int:
    """Bake an illumination lattice (resumes when --out holds a compatible one)."""
    from baking import bake
    from baking.lattice import Lattice

    from .images import check_output_path

    out = check_output_path(args.out, (".npz",))
    config = _bake_config(args)
    vol = _load_volume(args)
    try:
        lattice = bake(vol, config, out=out, workers=args.workers, progress=True,
                       scheduler=args.scheduler)
    except KeyboardInterrupt:
        if out.exists():
            done = Lattice.load(out)
            print(f"isolume: interrupted; {int((done.samples > 0).sum()):,} finished texels "
                  f"saved in {out}; run the same command again to resume", file=sys.stderr)
        return 130
    plan, stats = lattice.meta["plan"], lattice.meta["stats"]
    total = plan["total_texels"]
    print(f"wrote {out}: {plan['active_texels']:,} of {total:,} texels active "
          f"({plan['active_texels'] / total:.1%}), {len(plan['levels'])} levels, "
          f"{stats['rays_traced']:,} rays in {stats['bake_seconds']:.1f} s "
          f"({stats['rays_traced'] / max(stats['bake_seconds'], 1e-9) / 1e6:.2f} Mrays/s)")
    if args.scheduler:
        moved = lattice.meta["cluster"]
        print(f"cluster: {moved['tasks']:,} tasks, {moved['bytes_sent'] / 1e6:.1f} MB sent and "
              f"{moved['bytes_returned'] / 1e6:.1f} MB returned (+ {moved['job_bytes'] / 1e6:.1f} "
              f"MB to each worker once), {moved['scene_builds']} level scenes built")
    return 0


COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "info": cmd_info,
    "render": cmd_render,
    "bake": cmd_bake,
}

COMMAND_MODULES = {
    "view": "app.viewer",
    "reference": "app.reference",
    "chart": "app.charts",
    "bench": "app.bench",
}
"""Commands that live in their own modules. Each module provides ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``, and is imported only when present."""


def _command_module(name: str):
    import importlib
    import importlib.util

    module = COMMAND_MODULES[name]
    if importlib.util.find_spec(module) is None:
        return None
    return importlib.import_module(module)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    from baking.config import DEFAULT_ENV

    parser = argparse.ArgumentParser(
        prog="isolume", description="Isosurfaces with precomputed global illumination."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("info", help="describe a volume and suggest isovalues")
    _add_volume_options(p, optional=False)
    p = sub.add_parser("render", help="render an isosurface off-screen to PNG or EXR")
    _add_volume_options(p, optional=True)
    p.add_argument("--out", required=True, help="FILE.png (sRGB) or FILE.exr (linear)")
    _add_render_options(p)
    p = sub.add_parser("bake", help="bake an illumination lattice with Embree path tracing")
    _add_volume_options(p, optional=False)
    p.add_argument("--out", required=True, help="lattice file FILE.npz (resumed if present)")
    p.add_argument("--mode", default="irradiance", choices=["irradiance", "sh"])
    p.add_argument("--sh-order", type=int, default=5, help="SH bands (n² coefficients)")
    p.add_argument("--samples", type=int, default=100,
                   help="paths per texel (the minimum, with --target-error)")
    p.add_argument("--target-error", type=float, default=None, metavar="E",
                   help="sample each texel until its relative standard error is below E")
    p.add_argument("--max-samples", type=int, default=4096,
                   help="cap on paths per texel with --target-error")
    p.add_argument("--bounces", type=int, default=2, help="diffuse bounces (0 = direct)")
    p.add_argument("--albedo", default="0.8", help="A or R,G,B")
    p.add_argument("--scale", type=float, default=1.0, help="texels per voxel per axis")
    p.add_argument("--iso-range", type=float, nargs=2, metavar=("LO", "HI"))
    p.add_argument("--env", default=DEFAULT_ENV,
                   help="constant:R,G,B | sky[:k=v,...] | FILE.exr/.hdr[@angular] | none "
                   f"(default {DEFAULT_ENV})")
    p.add_argument("--light", action="append", metavar="SPEC",
                   help="point:X,Y,Z:R,G,B or dir:X,Y,Z:R,G,B (repeatable)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-levels", type=int, default=64, metavar="K",
                   help="cap on isovalue levels (fewer: faster, texels move farther onto "
                   "their levels)")
    p.add_argument("--max-move", type=float, default=None, metavar="VOXELS",
                   help="level spacing: texels move at most this far onto their levels "
                   "(default: from the samples, 0.5 voxel at 256 paths, and the level count "
                   "capped by the scenes' cost)")
    p.add_argument("--direct-light", choices=["pixels", "lattice"], default=None,
                   help="where the direct light of --light lights and the sky's sun goes: "
                   "pixels (shaded exactly per pixel by render/view, the lattice keeps their "
                   "bounces; the default when there is one; --mode sh: the sun, which turns "
                   "with the sky, and two transfer vectors, asked for explicitly) or lattice "
                   "(all in the lattice)")
    p.add_argument("--workers", type=int, default=None, help="threads (default: all cores)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="trace on a Dask cluster: its scheduler (tcp://host:8786), or local:N "
                   "for N worker processes here; the same lattice (pip install "
                   "'isolume[cluster]')")
    p.add_argument("--flip-normals", action="store_true", help="material less dense than air")
    for name in COMMAND_MODULES:
        module = _command_module(name)
        if module is not None:
            p = sub.add_parser(name, help=module.HELP)
            module.add_arguments(p)
    return parser


def _join_negative_axes(argv: Sequence[str]) -> list[str]:
    """``--up -z`` as ``--up=-z``: argparse would take ``-z`` for an option."""
    out, rest = [], list(argv)
    while rest:
        word = rest.pop(0)
        if word == "--up" and rest and rest[0] in ("-x", "-y", "-z"):
            word = f"--up={rest.pop(0)}"
        out.append(word)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``isolume`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(_join_negative_axes(sys.argv[1:] if argv is None else argv))
    command = COMMANDS.get(args.command) or _command_module(args.command).run
    try:
        return command(args)
    except _user_errors() as exc:
        message = " ".join(str(exc).split())
        print(f"isolume: error: {message}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("isolume: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    # run the imported module's main, so that command modules and this entry point share
    # one set of error classes (under `python -m`, this file is a second copy, __main__)
    from app.cli import main as _main

    sys.exit(_main())
