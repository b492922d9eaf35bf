"""How ``render`` and ``movie`` shade a picture from their options: the render settings,
the light traced for the view when there is no lattice, the SH environment."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.options import (
    CLIError,
    check_picture_memory,
    environment_coefficients,
    floats,
    parse_albedo,
    parse_exposure,
    view_light,
)
from isolume.app.state import light_settings

if TYPE_CHECKING:
    from isolume.app.render.settings import RenderSettings
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice, LatticeOnFile


@dataclass(frozen=True)
class Look:
    """How ``render`` (and each frame of ``movie``) shades its picture.

    Attributes:
        settings: the picture's `app.render.settings.RenderSettings`.
        traced: the `BakeConfig` of the light traced for the view (no lattice), or None.
        env_coeffs: (n², 3) SH coefficients of the environment ("sh"), or None.
    """

    settings: RenderSettings
    traced: BakeConfig | None = None
    env_coeffs: np.ndarray | None = None


def shading_look(args: argparse.Namespace, vol: volumes.Volume,
                 lattice: Lattice | HeldLattice | LatticeOnFile | None,
                 size: tuple[int, int], per: str = "view") -> Look:
    """The `Look` of the render options `args` for `vol` and `lattice` (None: none) in a
    `size` (width, height) picture; `CLIError` for options that contradict each other or
    the lattice, a bad ``--exposure``, or a picture whose light takes more memory than is
    available (`check_picture_memory`). A lattice that records no bake config is shown
    with the default albedo. `per` ("view" or "frame") says, in the errors, what is traced
    without a lattice."""
    from isolume.app.render.settings import LATTICE_MODES, RenderSettings

    shading = args.shading or (lattice.kind if lattice is not None else "irradiance")
    config = lattice.config if lattice is not None else None
    if lattice is not None and lattice.kind == "irradiance" and (args.env or args.light):
        lighting = "lighting not recorded" if config is None else config.lighting_text
        raise CLIError(f"--env/--light: {args.lattice} holds irradiance baked under its own "
                       f"lighting ({lighting}); bake again for other light, or leave out "
                       "--lattice")
    _check_lattice_options(args, lattice, shading)
    traced = view_light(args, vol) if lattice is None and shading == "irradiance" else None
    if args.albedo is not None:
        albedo = parse_albedo(args.albedo)
    else:
        albedo = config.albedo if config is not None else (0.8, 0.8, 0.8)
    try:
        settings = RenderSettings(
            size=size, shading=shading, exposure=parse_exposure(args.exposure),
            auto_exposure=not args.no_auto_exposure, tonemap=args.tonemap, albedo=albedo,
            env_rotation=floats(args.env_rotation, 2, "--env-rotation"),
            **light_settings(args.light_angles, lattice))
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    if shading in LATTICE_MODES and lattice is None and traced is None:
        where = "the view" if per == "view" else "each frame"
        raise CLIError(f"--shading {shading} needs --lattice FILE (make one with isolume "
                       f"bake); without one, irradiance is traced for {where}")
    check_picture_memory(size, "traced" if traced is not None
                         else "lattice" if shading in LATTICE_MODES else "local")
    env_coeffs = None
    if shading == "sh" and lattice is not None:
        env_coeffs = environment_coefficients(args.env, lattice, args.sh_window)
    return Look(settings, traced, env_coeffs)


def _check_lattice_options(args: argparse.Namespace,
                           lattice: Lattice | HeldLattice | LatticeOnFile | None,
                           shading: str) -> None:
    """`CLIError` (one line) for options a lattice would leave unused: a ``--shading``
    that reads the other kind of lattice (``sh`` with an irradiance one, the irradiance
    modes with an SH one), ``--light`` with an SH one (its transfer holds no point
    or directional light), ``--env-rotation`` with an irradiance one (its light is baked
    in place; a saved view's turned light, ``--state``, sets it for the sun drawn per
    pixel, and is not refused)."""
    from isolume.app.render.settings import SHADING_MODES

    if lattice is None:
        return
    mode = SHADING_MODES.get(shading)  # an unknown one: RenderSettings says so
    want = mode.lattice_kind if mode is not None else None
    if want is not None and lattice.kind != want:
        made = "isolume bake --mode sh" if want == "sh" else "isolume bake, without --mode sh"
        raise CLIError(f"--shading {shading} needs an {'SH' if want == 'sh' else want} "
                       f"lattice ({made}); {args.lattice} holds {lattice.kind}")
    if lattice.kind == "sh" and args.light:
        raise CLIError(f"--light: {args.lattice} is an SH lattice, whose transfer holds the "
                       "environment's light only; bake the lights into an irradiance "
                       "lattice (isolume bake --light), or leave out --lattice")
    turned = floats(args.env_rotation, 2, "--env-rotation") != (0.0, 0.0)
    if lattice.kind == "irradiance" and turned and not getattr(args, "state", None):
        raise CLIError(f"--env-rotation {args.env_rotation}: {args.lattice} holds irradiance "
                       "baked under its own lighting, which cannot turn; turn the light "
                       "with an SH lattice (isolume bake --mode sh), or leave out --lattice")

