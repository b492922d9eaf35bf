"""The ``info``, ``render`` and ``bake`` commands (the others live in their own modules:
`app.cli.COMMAND_MODULES`)."""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.look import shading_look
from isolume.app.options import (
    EXIT_INTERRUPTED,
    CLIError,
    bake_config,
    check_picture_memory,
    check_served,
    isovalue,
    load_lattice,
    load_volume,
    parse_size,
)
from isolume.volumes.errors import interrupted_by

if TYPE_CHECKING:
    from isolume.app.render.offscreen import Reuse
    from isolume.app.render.settings import Frame, RenderSettings
    from isolume.baking.bake import BakeOutlook
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.baking.plan_lattice import PlanLattice


def cmd_info(args: argparse.Namespace) -> int:
    """Print dimensions, spacing, value range, histogram and suggested isovalues; of a
    lattice file, what it holds (`app.lattice_info`)."""
    from isolume.app.lattice_info import describe_lattice, is_lattice_file
    from isolume.volumes.stats import VolumeInfo

    if isinstance(args.volume, str) and is_lattice_file(args.volume):
        print(describe_lattice(args.volume))
        return 0
    print(VolumeInfo.of(load_volume(args)))
    return 0


@dataclass(frozen=True)
class Rendered:
    """A picture `render_picture` drew.

    Attributes:
        frame: the `app.render.settings.Frame` (sRGB uint8 and linear float32 pixels).
        mesh: the isosurface drawn (`volumes.Mesh`).
        volume: the volume; iso: the isovalue, field units.
        settings: the `RenderSettings`; traced: the `BakeConfig` of the light traced for
            the view (no lattice), or None.
    """

    frame: Frame
    mesh: volumes.Mesh
    volume: volumes.Volume
    iso: float
    settings: RenderSettings
    traced: BakeConfig | None

    def summary(self) -> str:
        """One line: size, volume, isovalue, triangles, shading, lighting, exposure."""
        settings, traced = self.settings, self.traced
        lighting = f", lighting {traced.lighting_text}" if traced is not None else ""
        return (f"{settings.size[0]}x{settings.size[1]}, {self.volume.name} at iso "
                f"{self.iso:.6g}, {len(self.mesh.faces):,} triangles, shading "
                f"{settings.shading}{lighting}, exposure {self.frame.exposure:.3g}")


def render_picture(args: argparse.Namespace, reuse: Reuse | None = None) -> Rendered:
    """The picture of the ``render`` options `args` (the command's and the Python API's
    one way to a picture); `reuse`: an `app.render.offscreen.Reuse` that keeps the GL
    context and the surface for the next call, or None."""
    from isolume.app.render.camera import parse_view
    from isolume.app.render.offscreen import render_volume

    try:  # before any work: a size beyond the memory is refused at once
        view, size = parse_view(args.view), parse_size(args.size)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    check_picture_memory(size, "local")
    vol = load_volume(args)
    lattice = load_lattice(args.lattice, vol, args.env, whole=False)
    look = shading_look(args, vol, lattice, size)
    iso = isovalue(vol, args.iso)
    check_served(lattice, iso, args.lattice)
    frame, mesh = render_volume(
        vol, iso, look.settings, view=view, camera=args.camera,
        backend=args.gl, normals=args.normals, flip_normals=args.flip_normals,
        lattice=lattice, env_coeffs=look.env_coeffs, view_light=look.traced,
        view_spread=args.spread, shadows=args.shadows, workers=args.workers, progress=True,
        reuse=reuse,
    )
    if mesh.empty:
        print(f"isolume: warning: {mesh.message}", file=sys.stderr)
    elif not frame.mask.any():
        print("isolume: warning: the surface covers no pixel of the picture (the camera looks "
              "away from it, or is too far: --view AZ,EL[,DIST], DIST in the box's "
              "diagonals)", file=sys.stderr)
    return Rendered(frame, mesh, vol, iso, look.settings, look.traced)


def cmd_render(args: argparse.Namespace) -> int:
    """Render the isosurface off-screen to PNG (sRGB) or EXR (linear radiance)."""
    from isolume.app.allocator import for_pictures
    from isolume.app.render.images import check_output_path, write_image

    if args.out is None:
        raise CLIError("render: --out FILE.png or FILE.exr is required (or --state FILE)")
    out = check_output_path(args.out)
    for_pictures()
    rendered = render_picture(args)
    write_image(out, rendered.frame.linear, rendered.frame.srgb)
    print(f"wrote {out} ({rendered.summary()})")
    return 0


CHEAPER_AFTER_MINUTES = 1.0
"""A bake expected to take longer than this says how to make it cheaper."""


def say_outlook(outlook: BakeOutlook, config: BakeConfig) -> None:
    """Tell, before any path, what a bake of `config` will trace and roughly how long it
    will take (`baking.bake.BakeOutlook`), and how to make it cheaper when that exceeds
    `CHEAPER_AFTER_MINUTES`."""
    if outlook.resumed:
        print(f"bake: resuming: {outlook.resumed:,} of the {outlook.texels:,} texels have "
              "paths in the --out file already", file=sys.stderr, flush=True)
    line = (f"bake: {outlook.texels:,} texels on {outlook.levels} levels, "
            f"{outlook.paths:,} paths to trace")
    minutes = outlook.minutes()
    if minutes is not None:
        threads = "1 thread" if outlook.threads == 1 else f"{outlook.threads} threads"
        line += f", roughly {minutes:.1f} min on {threads}"
    print(line, file=sys.stderr, flush=True)
    if minutes is not None and minutes > CHEAPER_AFTER_MINUTES:
        print(f"bake: cheaper: {cheaper_options(config)}, or isolume view (bakes what is "
              "visible first); Ctrl-C keeps the finished texels and the same command "
              "resumes", file=sys.stderr, flush=True)


def cheaper_options(config: BakeConfig) -> str:
    """The options that make a bake of `config` cheaper: an iso range, half its paths
    per texel (while it has more than one; beside its texel error, which ``--samples``
    alone would drop; with a noise target, twice the target), a texel error (where it has
    none and no noise target: the two are not combined) and half its lattice scale (while
    that is allowed: `baking.config.SCALES`)."""
    from isolume.baking.config import DEFAULT_TEXEL_ERROR, SCALES

    options = ["--iso-range LO HI around the isovalues you will show"]
    if config.target_error is not None:
        options.append(f"--target-error {min(2 * config.target_error, 0.5):g}")
    elif config.samples > 1:
        texels = (f" --texel-error {config.texel_error:g}"
                  if config.texel_error is not None else "")
        options.append(f"--samples {config.samples // 2}{texels}")
    if config.texel_error is None and config.target_error is None:
        options.append(f"--texel-error {DEFAULT_TEXEL_ERROR:g}")
    if config.scale / 2 >= SCALES[0]:
        options.append(f"--scale {config.scale / 2:g}")
    return ", ".join(options)


def bake_lattice(args: argparse.Namespace, *, dense: bool = False,
                 keep_interrupted: bool = False) -> Lattice | PlanLattice:
    """The lattice of the ``bake`` options `args` (the command's and the Python API's one
    way to a bake): written to ``args.out`` when it is given (resumed when it holds a
    compatible one), said beforehand (`say_outlook`); `dense` and `keep_interrupted` as
    `baking.bake`."""
    from isolume.app.render.images import check_output_path
    from isolume.baking import bake

    out = check_output_path(args.out, (".npz",)) if args.out is not None else None
    config = bake_config(args)
    scene_memory = scene_memory_bytes(args.scene_memory)
    vol = load_volume(args)
    return bake(vol, config, out=out, workers=args.workers, progress=True,
                scheduler=args.scheduler, outlook=lambda o: say_outlook(o, config),
                dense=dense, keep_interrupted=keep_interrupted, scene_memory=scene_memory)


def scene_memory_bytes(gigabytes: float | None) -> float | None:
    """Bytes of ``--scene-memory GB`` (None: the bake's default).

    Raises:
        CLIError: not a finite size of 0 or more.
    """
    if gigabytes is None:
        return None
    if not (math.isfinite(gigabytes) and gigabytes >= 0):
        raise CLIError(f"--scene-memory {gigabytes:g}: expected a size in GB, 0 or more")
    return gigabytes * 1e9


def _held_paths(lattice) -> int:
    """The paths traced into a baked `lattice`'s texels: its samples, less the `samples`
    a texel filled from the half lattice is given without a path traced
    (`baking.fills.fill`); the same for a bake interrupted and resumed as for one run."""
    held = int(lattice.samples.sum(dtype=np.int64))
    filled = lattice.meta.get("filled")
    if filled is not None and lattice.config is not None:
        held -= int(filled["filled"]) * lattice.config.samples
    return held


def cmd_bake(args: argparse.Namespace) -> int:
    """Bake an illumination lattice (resumes when --out holds a compatible one)."""
    from isolume.baking.errors import BakeInterrupted, SaveAbandoned

    out = args.out
    try:
        lattice = bake_lattice(args)
    except BakeInterrupted as stop:
        print(f"isolume: interrupted; {stop.finished:,} finished texels saved in {out}; "
              "run the same command again to resume (and to compress what a Ctrl-C saved "
              "uncompressed)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except SaveAbandoned:
        kept = (f"{out} keeps the texels of its last save" if Path(out).exists()
                else f"{out} not written")
        print(f"isolume: interrupted again while saving: the texels finished since the "
              f"last save were not saved; {kept}; run the same command again to bake them",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    except (KeyboardInterrupt, SystemError) as exc:  # before the tracing: nothing new
        if not interrupted_by(exc):
            raise
        if Path(out).exists():
            print(f"isolume: interrupted; {out} keeps the texels of its last save; run the "
                  "same command again to resume", file=sys.stderr)
        else:
            print(f"isolume: interrupted before any path was traced; {out} not written",
                  file=sys.stderr)
        return EXIT_INTERRUPTED
    plan, stats = lattice.meta["plan"], lattice.meta["stats"]
    total = plan["total_texels"]
    print(f"wrote {out}: {plan['active_texels']:,} of {total:,} texels active "
          f"({plan['active_texels'] / total:.1%}), {len(plan['levels'])} levels, "
          f"{stats['rays_traced']:,} rays in {stats['bake_seconds']:.1f} s "
          f"({stats['rays_traced'] / max(stats['bake_seconds'], 1e-9) / 1e6:.2f} Mrays/s)")
    held = _held_paths(lattice)
    per_texel = f"{held / max(plan['active_texels'], 1):.1f}"
    runs = (f" ({stats['paths']:,} traced over its runs: an interruption loses the paths "
            "of texels not yet saved)" if stats["paths"] != held else "")
    if lattice.config is not None and lattice.config.target_error is not None:
        print(f"noise target {lattice.config.target_error:g}: {held:,} paths, {per_texel} a "
              f"texel on average{runs}")
    if "filled" in lattice.meta:
        filled = lattice.meta["filled"]
        print(f"texel error {filled['texel_error']:g}: {filled['fine_bricks']:,} of "
              f"{filled['bricks']:,} bricks traced whole, {filled['filled']:,} of "
              f"{filled['count']:,} texels filled from the half lattice, {per_texel} paths a "
              f"texel on average{runs}")
    if args.scheduler:
        moved = lattice.meta["cluster"]
        print(f"cluster: {moved['tasks']:,} tasks, {moved['bytes_sent'] / 1e6:.1f} MB sent and "
              f"{moved['bytes_returned'] / 1e6:.1f} MB returned (+ {moved['job_bytes'] / 1e6:.1f} "
              f"MB to each worker once), {moved['scene_builds']} level scenes built")
    return 0
