"""The command line's options and their parsing, shared by every command module.

Each parser turns one option's text into a checked value or raises `CLIError`, whose
message names the option, the value and what was expected.
"""

from __future__ import annotations

import argparse
import os
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.environment import Environment
    from isolume.baking.lattice import Lattice
    from isolume.baking.lighting import Lighting
    from isolume.baking.view_texels import HeldLattice, LatticeOnFile

EXIT_USER_ERROR = 2
"""Exit status of a command that ends on bad input."""
EXIT_INTERRUPTED = 130
"""Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it)."""


class CLIError(IsolumeError):
    """A bad command-line value; the message says what was expected."""


def choice_error(action: argparse.Action, name: str, value: object) -> str | None:
    """The one line saying that `value` (None: the option's default) is not among the
    choices of the option `action`, given as `name`, as its parser would refuse it; None
    where it is."""
    if action.choices is None or value is None or value in action.choices:
        return None
    return f"{name}={value!r}: expected one of {', '.join(map(str, action.choices))}"


def floats(text: str, count: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise CLIError(f"{what} {text!r}: expected {count} comma-separated numbers") from None
    if len(values) != count or not np.isfinite(values).all():
        raise CLIError(f"{what} {text!r}: expected {count} comma-separated finite numbers")
    return values


PIXEL_BYTES = {"local": 110, "lattice": 230, "traced": 510}
"""Peak memory a pixel of a picture takes, in bytes, by where its light comes from: shading
computed per pixel alone ("local", e.g. lambert: the least any picture takes), a lattice
read ("lattice") or global illumination traced for the view ("traced"). Measured as the
slope of ``render``'s peak resident memory from 1024x1024 to 2048x2048 with the surface
filling the picture (105, 225 and 505 bytes), PNG or EXR alike; `check_picture_memory`
weighs them against the memory available."""
PIXEL_BYTES_WHY = {"local": "at the least", "lattice": "reading a lattice",
                   "traced": "tracing the view's light"}
"""What each estimate of `PIXEL_BYTES` is, in `check_picture_memory`'s message."""


def parse_size(text: str) -> tuple[int, int]:
    """(width, height) of ``--size WxH``: each 1 to 16384 pixels (the commands that
    make the picture check that it fits in memory, `check_picture_memory`)."""
    parts = text.lower().split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise CLIError(f"--size {text!r}: expected WxH, e.g. 512x512") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise CLIError(f"--size {text!r}: width and height must be between 1 and 16384")
    return w, h


def check_picture_memory(size: tuple[int, int], light: str) -> None:
    """`CLIError` when a `size` (width, height) picture whose light comes from `light` (a
    key of `PIXEL_BYTES`) would take more memory than this machine has available."""
    from isolume.volumes.io.common import available_memory

    w, h = size
    need = w * h * PIXEL_BYTES[light]
    free = available_memory()
    if free is not None and need > free:
        raise CLIError(f"--size {w}x{h}: the picture needs about {need / 1e9:.3g} GB of "
                       f"memory ({PIXEL_BYTES[light]} bytes a pixel {PIXEL_BYTES_WHY[light]}),"
                       f" more than the {free / 1e9:.3g} GB available; expected a smaller "
                       "size")


def parse_dims(text: str) -> tuple[int, int, int]:
    """(X, Y, Z) voxels of ``--dims X,Y,Z``: three whole numbers ≥ 1."""
    try:
        dims = tuple(int(v) for v in text.split(","))
    except ValueError:
        dims = ()
    if len(dims) != 3 or min(dims) < 1:
        raise CLIError(f"--dims {text!r}: expected X,Y,Z, three whole numbers of voxels ≥ 1")
    return dims


def parse_exposure(exposure: float) -> float:
    """``--exposure``: a positive finite linear multiplier."""
    if not (np.isfinite(exposure) and exposure > 0):
        raise CLIError(f"--exposure {exposure:g}: expected a positive finite number")
    return exposure


def load_volume(args: argparse.Namespace) -> volumes.Volume:
    """The volume of the options `add_volume_options` adds: the file or synthetic spec,
    raw dims and type, spacing, the part (``--crop``, ``--downsample``, ``--level``),
    then turned by ``--up``; a `volumes.Volume` in ``args.volume`` (the Python API's,
    loaded with those options already) as it is."""
    if isinstance(args.volume, volumes.Volume):
        return args.volume
    options = {}
    if getattr(args, "dims", None):
        options["dims"] = parse_dims(args.dims)
    if getattr(args, "dtype", None):
        options["dtype"] = args.dtype
    if getattr(args, "spacing", None):
        options["spacing"] = floats(args.spacing, 3, "--spacing")
    if getattr(args, "origin", None):
        options["origin"] = floats(args.origin, 3, "--origin")
    if getattr(args, "volume_level", None) is not None:
        options["level"] = args.volume_level
    volume = volumes.load(args.volume, crop=getattr(args, "volume_crop", None),
                          downsample=getattr(args, "volume_downsample", 1), **options)
    if getattr(args, "up", None):
        volume = volumes.turn_up(volume, args.up)
    return volume


def isovalue(volume: volumes.Volume, iso: float | None) -> float:
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


def load_lattice(path: str | os.PathLike[str] | Lattice | None, volume: volumes.Volume,
                 env: str | None, whole: bool = True
                 ) -> Lattice | HeldLattice | LatticeOnFile | None:
    """The lattice at `path` checked against `volume` and shown under the environment
    `env` (``--env``, `_shown_under`), or None: with `whole`, its computed texels (a
    `baking.view_texels.HeldLattice`: memory follows them, not the box); else the file
    opened, no texel read (a `baking.view_texels.LatticeOnFile`: a picture reads the
    texels its pixels need, `app.render.offscreen.render_volume`). A lattice in memory (a
    `baking.Lattice`, the Python API's) is checked against `volume` and not copied."""
    if path is None:
        return None
    from isolume.baking.lattice import Lattice, check_identity
    from isolume.baking.view_texels import LatticeOnFile

    if isinstance(path, Lattice):
        check_identity(path.meta, volume, "the lattice given")
        return _shown_under(path, env)

    opened = LatticeOnFile.open(path, volume)
    return _shown_under(opened.held(fill=True) if whole else opened, env)


def _shown_under(lattice: Lattice | HeldLattice | LatticeOnFile | None, spec: str | None
                ) -> Lattice | HeldLattice | LatticeOnFile | None:
    """`lattice` as a picture shows it under the environment `spec` (``--env``; None: the
    baked one). An SH lattice that leaves its sun to the pixels (baked with direct light
    "pixels": its transfer split, `environment_coefficients`) takes the sun of `spec` for
    its pixels, as its transfer takes the sky of `spec`: the same lattice with `spec` as
    its config's environment (its arrays shared). Any other lattice is returned as it is
    (an irradiance lattice holds its lighting: ``--env`` is refused with it)."""
    import copy
    import dataclasses

    from isolume.app.render.lights import lattice_direct_lights
    from isolume.baking.lighting import lighting_of
    from isolume.baking.view_texels import HeldLattice

    if spec is None or lattice is None or lattice.kind != "sh" \
            or not lattice_direct_lights(lattice):
        return lattice
    lighting_of(spec)  # a spec that does not parse says why itself
    try:
        config = dataclasses.replace(lattice.config, env=spec)
    except (ValueError, IsolumeError):
        raise CLIError(f"--env {spec}: this SH lattice draws its sky's sun per pixel (baked "
                       "with --direct-light pixels): show it under a procedural sky with a sun "
                       "(sky:sun=S,sun_az=A,sun_el=E)") from None
    if isinstance(lattice, HeldLattice):
        shown = copy.copy(lattice)
        shown.config = config
        return shown
    return dataclasses.replace(lattice, config=config)


def check_served(lattice: Lattice | HeldLattice | LatticeOnFile | None, iso: float,
                 source: str | None) -> None:
    """`CLIError` (one line) when `lattice` (from file `source`; None: nothing to check)
    was not baked for isovalue `iso` (`baking.plan.outside_served_range`)."""
    if lattice is None:
        return
    from isolume.baking.plan import outside_served_range

    refused = outside_served_range(lattice.meta, iso, source)
    if refused:
        raise CLIError(refused)


def environment_coefficients(spec: str | None, lattice: Lattice | HeldLattice | LatticeOnFile,
                             window: str) -> np.ndarray:
    """(n², 3) SH coefficients of the display environment for an SH lattice."""
    from isolume.baking import sh
    from isolume.baking.lighting import lighting_of

    baked = lattice.config.lighting.environment if lattice.config is not None else None
    order = int(lattice.meta["sh_order"])
    try:  # a split transfer (sun per pixel) also takes the sky without its sun
        env = (lighting_of(spec).environment if spec
               else baked or lighting_of("constant:1,1,1").environment)
        if spec:
            check_sends_light(spec, env)
        return sh.display_coefficients(env, order, sh.transfer_blocks(lattice),
                                       window=None if window == "none" else window)
    except CLIError:
        raise
    except ValueError as exc:
        raise CLIError(f"--env {spec or env.spec}: {exc}") from None


def add_volume_options(p: argparse.ArgumentParser, optional: bool) -> None:
    p.add_argument(
        "volume", nargs="?" if optional else None, default=None,
        help="volume file or synthetic:NAME[:SIZE]"
        + (f" (default {volumes.DEFAULT})" if optional else ""),
    )
    p.add_argument("--dims", help="X,Y,Z for raw files whose name does not say")
    p.add_argument("--dtype", help="sample type for raw files, e.g. uint8, int16, float32")
    p.add_argument("--spacing", help="voxel size X,Y,Z (overrides the file's, or a "
                   "synthetic volume's)")
    p.add_argument("--origin", help="world position X,Y,Z of the first voxel's centre "
                   "(overrides the file's or a synthetic volume's; e.g. 0,0,0 for a file "
                   "placed far from the world origin)")
    p.add_argument("--up", metavar="AXIS", default=None,
                   help="the volume's axis that points up: x, y, z, -x, -y or -z (after the "
                   "orientation its header gives; e.g. -z for raw slices that run top "
                   "to bottom; default z)")
    add_part_options(p)


def add_part_options(p: argparse.ArgumentParser) -> None:
    """``--crop``, ``--downsample`` and ``--level``: which part of the volume to read (into
    ``args.volume_crop``, ``volume_downsample``, ``volume_level``, read by `load_volume`)."""
    p.add_argument("--crop", dest="volume_crop", metavar="X0:X1,Y0:Y1,Z0:Z1", default=None,
                   help="read only these voxels: index ranges along x, y, z from 0, end "
                   "exclusive, of the volume as its header places it (before --up); ':' "
                   "for a whole axis, '100:' from voxel 100 on; the world position is kept")
    p.add_argument("--downsample", dest="volume_downsample", metavar="N", type=int, default=1,
                   help="means of N×N×N-voxel blocks (after --crop; spacing × N, the last "
                   "voxels that fill no whole block left out; default 1)")
    p.add_argument("--level", dest="volume_level", metavar="K", type=int, default=None,
                   help="level of an OME-Zarr multiscale image (0: full resolution, the "
                   "default; --crop and --downsample count in its voxels)")


def add_light_options(p: argparse.ArgumentParser, traced_for: str) -> None:
    """The options ``render``, ``movie`` and ``export`` share: the isovalue, the lattice,
    the lighting and the light traced for `traced_for` without a lattice ("this view"),
    the albedo, the SH environment's turn and window, exposure and tone curve, normals."""
    from isolume.app.render.settings import TONEMAPS
    from isolume.app.render.view_gi import DEFAULT_PATHS, SPREADS
    from isolume.baking.config import DEFAULT_ALBEDO, DEFAULT_BOUNCES, DEFAULT_ENV

    p.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    p.add_argument("--lattice", help="illumination lattice from `isolume bake` (default: "
                   f"global illumination traced for {traced_for})")
    p.add_argument("--env", default=None,
                   help="the lighting: constant:R,G,B | sky[:k=v,...] | FILE.exr/.hdr[@angular]"
                   f" | none (default: the lattice's with --lattice, else {DEFAULT_ENV})")
    p.add_argument("--light", action="append", metavar="SPEC",
                   help="point:X,Y,Z:R,G,B or dir:X,Y,Z:R,G,B (repeatable; without "
                   "--lattice; default none)")
    p.add_argument("--samples", type=int, default=None,
                   help="paths per texel of the traced global illumination, on average: a "
                   "few each, the rest where the picture's noise is (without --lattice; "
                   f"default {DEFAULT_PATHS})")
    p.add_argument("--spread", choices=SPREADS, default=SPREADS[0],
                   help="how those paths are spread over the texels: where the picture's "
                   "noise is (noise, the default) or --samples at every texel (even)")
    p.add_argument("--bounces", type=int, default=DEFAULT_BOUNCES,
                   help=f"diffuse bounces of that illumination (default {DEFAULT_BOUNCES})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--workers", type=int, default=None,
                   help=WORKERS_HELP)
    p.add_argument("--albedo", default=None,
                   help="A or R,G,B diffuse reflectance (default: the lattice's, else "
                   f"{DEFAULT_ALBEDO})")
    p.add_argument("--env-rotation", default="0,0",
                   help="AZ,EL degrees the environment of an SH lattice turns by (default 0,0)")
    p.add_argument("--sh-window", default="none", choices=["none", "hanning", "lanczos"],
                   help="window against ringing of the environment's SH projection (SH "
                   "lattices; default none)")
    p.add_argument("--exposure", type=float, default=1.0,
                   help="linear exposure multiplier on the automatic exposure, which brings "
                   "the area-weighted log-average luminance of the surface to middle grey "
                   "(default 1)")
    p.add_argument("--no-auto-exposure", action="store_true",
                   help="no automatic exposure: --exposure is the whole linear scale")
    p.add_argument("--tonemap", default="aces", choices=list(TONEMAPS),
                   help="tone curve from exposed radiance to the displayed colours "
                   "(default aces)")
    p.add_argument("--normals", default="smooth", choices=["smooth", "gradient"],
                   help="normals: B-spline-smoothed gradient (the paper's) or plain central "
                   "differences (default smooth)")
    p.add_argument("--flip-normals", action="store_true",
                   help="material less dense than air: normals (and the lit side) towards "
                   "higher values (default off)")


WORKERS_HELP = ("threads for all the command runs in parallel: tracing, the plan's kernels, "
                "Embree's builds, Mesa, BLAS (default: the cores this process may use)")


def add_timeline_option(p: argparse.ArgumentParser) -> None:
    """``--timeline FILE.json``: where the command's cores went, stage by stage
    (`volumes.cores.Timeline`; `isolume bench cores` reads it)."""
    p.add_argument("--timeline", metavar="FILE.json", default=None,
                   help="record each stage's wall and CPU time, every thread's, and the "
                   "work items, as JSON (isolume bench cores reads it)")


def add_render_options(p: argparse.ArgumentParser) -> None:
    """The options of a picture (``render``, ``movie``): `add_light_options` for this
    view, the shading mode, the size, the camera and the GL back end."""
    from isolume.app.render.settings import SHADING_MODES

    add_light_options(p, "this view")
    p.add_argument("--shading", default=None,
                   help=f"one of {', '.join(SHADING_MODES)} (default: the lattice's kind "
                   "with --lattice, else irradiance: global illumination traced for this "
                   "view)")
    p.add_argument("--size", default="512x512", help="WxH pixels (default 512x512)")
    p.add_argument("--view", default="30,30",
                   help="AZ,EL[,DIST]: azimuth and elevation (degrees) around the surface's "
                   "box, DIST in the box's diagonals (default 30,30 and as near as frames "
                   "the box)")
    p.add_argument("--gl", default="auto", choices=["auto", "egl", "osmesa"],
                   help="headless GL: EGL, OSMesa, or whichever works (auto)")
    p.add_argument("--shadows", default="traced", choices=["traced", "map"],
                   help="the sun's and the lights' direct light per pixel: traced rays, as "
                   "the reference (a second or two at 512x512), or the viewer's shadow maps "
                   "(default traced)")


def parse_albedo(text: str) -> tuple[float, float, float]:
    """``A`` or ``R,G,B`` in [0, 1] → RGB tuple."""
    parts = text.split(",")
    values = floats(text, len(parts), "--albedo") if len(parts) in (1, 3) else None
    if values is None:
        raise CLIError(f"--albedo {text!r}: expected A or R,G,B")
    if len(values) == 1:
        values = values * 3
    if min(values) < 0 or max(values) > 1:
        raise CLIError(f"--albedo {text!r}: reflectance must lie in [0, 1]")
    return values


def parse_lighting(env: str | None, lights: list[str] | None, default: str = ""
                   ) -> Lighting:
    """The `baking.lighting.Lighting` of ``--env`` (None: `default`; "none": no
    environment) and the ``--light`` specs (None: none), parsed once for the command.

    Raises:
        EnvSpecError, BakeError: a bad spec (one line, naming it).
    """
    from isolume.baking.lighting import lighting_of

    env = default if env is None else env
    lighting = lighting_of("" if env == "none" else env, tuple(lights or ()))
    if not lighting.lights and lighting.environment is not None:
        check_sends_light(env, lighting.environment)
    return lighting


def check_sends_light(spec: str, environment: Environment) -> None:
    """`CLIError` when `environment` (of the ``--env`` `spec`), the scene's only light,
    sends none: zero radiance in every direction (an all-black map)."""
    if not np.any(np.asarray(environment.mean_radiance) > 0):
        raise CLIError(f"nothing lights the scene: --env {spec} sends no light (its radiance "
                       "is 0 in every direction); give an environment that does and/or "
                       "--light")


def view_light(args: argparse.Namespace, volume: volumes.Volume) -> BakeConfig:
    """The `BakeConfig` of the global illumination ``render`` traces for its view (the
    lighting ``reference`` path-traces with the same arguments)."""
    from isolume.app.render.view_gi import DEFAULT_PATHS
    from isolume.baking.config import DEFAULT_ALBEDO, DEFAULT_ENV, BakeConfig

    samples = DEFAULT_PATHS if args.samples is None else args.samples
    if not 1 <= samples <= 4096:
        raise CLIError(f"--samples {samples}: expected 1 to 4096 paths per texel")
    return BakeConfig.lit_by(
        parse_lighting(args.env, args.light, DEFAULT_ENV),
        mode="irradiance", samples=samples, bounces=args.bounces,
        albedo=parse_albedo(args.albedo or str(DEFAULT_ALBEDO)), seed=args.seed,
        normals=args.normals,
        flip_normals=args.flip_normals,
    )


def bake_config(args: argparse.Namespace) -> BakeConfig:
    """The `BakeConfig` of ``isolume bake``'s options (`add_bake_options`)."""
    from isolume.baking.config import BakeConfig

    samples, target, texel = bake_paths(args.samples, args.target_error, args.texel_error,
                                        args.mode)
    return BakeConfig.lit_by(
        parse_lighting(args.env, args.light),
        mode=args.mode, sh_order=args.sh_order, samples=samples, bounces=args.bounces,
        albedo=parse_albedo(args.albedo), scale=args.scale,
        iso_range=tuple(args.iso_range) if args.iso_range else None, seed=args.seed,
        flip_normals=args.flip_normals, sides=args.sides, target_error=target,
        texel_error=texel, max_samples=max_paths(args.max_samples, samples, target),
        max_levels=args.max_levels, max_move=args.max_move, direct_light=args.direct_light,
    )


def max_paths(max_samples: int, samples: int, target: float | None) -> int:
    """``--max-samples`` `max_samples` as the bake config takes it: as given with a
    `target` error (the config refuses it below `samples`); without one, where it caps
    nothing, at least `samples` (its default may be below ``--samples``).

    Raises:
        CLIError: fewer than one path.
    """
    if max_samples < 1:
        raise CLIError(f"--max-samples {max_samples}: expected at least 1 path a texel")
    return max_samples if target is not None else max(max_samples, samples)


def bake_paths(samples: int | None, target: float | None, texel: float | None,
               mode: str = "irradiance") -> tuple[int, float | None, float | None]:
    """(samples, target error, texel error) of ``bake``'s ``--samples``,
    ``--target-error`` and ``--texel-error``:

    - a target: paths where the noise is (`baking.adaptive`) from a minimum of `samples`
      (`ADAPTIVE_MIN_SAMPLES` when not given);
    - a texel error: texels where the light varies (`baking.density`), `samples` paths a
      traced texel (`baking.config.TEXEL_SAMPLES` when not given);
    - `samples` alone: exactly `samples` paths a texel, every texel traced;
    - none of them: an irradiance bake to `baking.config.DEFAULT_TEXEL_ERROR` at
      `TEXEL_SAMPLES`; an SH bake (`mode` ``"sh"``, whose light turns: the texel judgement
      weighs the DC term only) exactly `baking.config.DEFAULT_SAMPLES` a texel."""
    from isolume.baking.config import DEFAULT_SAMPLES, DEFAULT_TEXEL_ERROR, TEXEL_SAMPLES

    if target is not None:
        return (ADAPTIVE_MIN_SAMPLES if samples is None else samples), target, texel
    if texel is not None:
        return (TEXEL_SAMPLES if samples is None else samples), None, texel
    if samples is not None:
        return samples, None, None
    if mode == "sh":
        return DEFAULT_SAMPLES, None, None
    return TEXEL_SAMPLES, None, DEFAULT_TEXEL_ERROR


ADAPTIVE_MIN_SAMPLES = 16
"""The fewest paths a texel of a bake to a noise target gets when ``--samples`` is not
given."""
DEFAULT_MAX_SAMPLES = 1024
"""The most paths a texel of a bake to a noise target gets (``--max-samples``)."""


def add_bake_options(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume bake`` after the volume's."""
    from isolume.baking.config import (
        DEFAULT_ALBEDO,
        DEFAULT_BOUNCES,
        DEFAULT_ENV,
        DEFAULT_SAMPLES,
        DEFAULT_TEXEL_ERROR,
        TEXEL_SAMPLES,
    )

    p.add_argument("--out", required=True, help="lattice file FILE.npz (resumed if present)")
    p.add_argument("--mode", default="irradiance", choices=["irradiance", "sh"],
                   help="irradiance (static lights) or SH radiance transfer (an environment "
                   "that can turn) (default irradiance)")
    p.add_argument("--sh-order", type=int, default=5, help="SH bands (n² coefficients)")
    p.add_argument("--samples", type=int, default=None, metavar="N",
                   help="paths per texel: alone, exactly N for every texel (a uniform "
                   f"lattice); with --texel-error, per traced texel (default "
                   f"{TEXEL_SAMPLES}); with --target-error, the fewest (default "
                   f"{ADAPTIVE_MIN_SAMPLES}). With none of the three: --texel-error "
                   f"{DEFAULT_TEXEL_ERROR:g} at {TEXEL_SAMPLES} paths (irradiance), exactly "
                   f"{DEFAULT_SAMPLES} (sh)")
    p.add_argument("--target-error", type=float, default=None, metavar="E",
                   help="paths where the noise is: texels get paths in doubling rounds, in "
                   "proportion to the spread of their paths, until each isosurface's noise "
                   "is E of its light level (e.g. 0.1)")
    p.add_argument("--texel-error", type=float, default=None, metavar="E",
                   help="texels where the light varies: a brick of the lattice is traced at "
                   "half resolution, its other texels filled from it, where that "
                   "reproduces its light within E of the scene's light level (default "
                   f"{DEFAULT_TEXEL_ERROR:g} for an irradiance bake that names no --samples "
                   "nor --target-error)")
    p.add_argument("--max-samples", type=int, default=DEFAULT_MAX_SAMPLES, metavar="N",
                   help="the most paths a texel gets with a target (default "
                   f"{DEFAULT_MAX_SAMPLES})")
    p.add_argument("--bounces", type=int, default=DEFAULT_BOUNCES,
                   help=f"diffuse bounces (0 = direct; default {DEFAULT_BOUNCES})")
    p.add_argument("--albedo", default=str(DEFAULT_ALBEDO),
                   help=f"A or R,G,B (default {DEFAULT_ALBEDO})")
    p.add_argument("--scale", type=float, default=1.0,
                   help="texels per voxel along the finest axis (cubes where voxels are not)")
    p.add_argument("--iso-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="bake only the texels of isovalues LO..HI (default: the isovalues "
                   "`isolume info` suggests, with a margin of a quarter of their spread on "
                   "either side)")
    p.add_argument("--env", default=DEFAULT_ENV,
                   help="constant:R,G,B | sky[:k=v,...] | FILE.exr/.hdr[@angular] | none "
                   f"(default {DEFAULT_ENV})")
    p.add_argument("--light", action="append", metavar="SPEC",
                   help="point:X,Y,Z:R,G,B or dir:X,Y,Z:R,G,B (repeatable)")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed: the same seed gives the same lattice with any "
                   "--workers (default 0)")
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
    p.add_argument("--workers", type=int, default=None, help=WORKERS_HELP)
    p.add_argument("--scene-memory", type=float, default=None, metavar="GB",
                   help="memory for level scenes kept between passes, so that each is built "
                   "once for the plan and every pass of the bake rather than once a pass (0: "
                   "one scene at a time; default a quarter of the memory available for a "
                   "bake to a texel error or a target, 0 for --samples N alone; threads "
                   "only: a --scheduler worker builds the scenes it traces)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="trace on a Dask cluster: its scheduler (tcp://host:8786), or local:N "
                   "for N worker processes here; the same lattice (pip install "
                   "'isolume[cluster]')")
    p.add_argument("--flip-normals", action="store_true", help="material less dense than air")
    p.add_argument("--sides", default="seen", choices=["seen", "normals"],
                   help="which side of the surface each texel is lit on: the side a camera "
                   "outside the volume sees (both, on alternate texels, where both can be "
                   "seen: sheets, scans cut by the box) or the side the normals point to "
                   "(default seen)")


def description_of(help_text: str) -> str:
    """A subcommand's one-line `help_text` (an argparse help string, "%%" for "%") as its
    description: capitalised, with a full stop."""
    text = help_text.replace("%%", "%")
    return text[:1].upper() + text[1:].rstrip(".") + "."
