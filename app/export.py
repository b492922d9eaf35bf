"""``isolume export``: the lit isosurface as a mesh file for Blender, three.js or ParaView.

The isosurface at the isovalue is extracted as ``isolume render`` extracts it (marching
cubes, smoothed-gradient normals), each vertex gets the outgoing radiance of the light
render shows (`app.export_light`: the lattice's, or global illumination traced for the
whole surface, plus the direct light render adds per pixel, with Embree shadow rays), and
the mesh goes to a .glb or .ply file with its display colours and its linear radiance
(`app.export_files`). The display colours are exposed and tone-mapped as render's pixels
are; the automatic exposure meters the whole surface (the vertices weighted by their
areas), where render meters the pixels of its view.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.options import (
    CLIError,
    add_light_options,
    add_volume_options,
    check_served,
    environment_coefficients,
    floats,
    isovalue,
    load_lattice,
    load_volume,
    parse_albedo,
    parse_exposure,
    view_light,
)

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig

HELP = "export the lit isosurface as a mesh with vertex colours (glTF .glb or PLY)"
DESCRIPTION = """\
Export the lit isosurface as a mesh file with per-vertex colours: glTF binary (.glb, for
Blender, three.js and web viewers) or PLY (.ply, for ParaView, MeshLab, Blender). Each
vertex carries the light render shows: the lattice's (--lattice), or global illumination
traced for the whole surface, plus the direct light of the sun and --light lights with
exact shadows. Colours are exposed and tone-mapped as render's pixels (glTF COLOR_0: the
linear display colour; PLY: 8-bit sRGB); the unexposed linear radiance rides along
(glTF _RADIANCE, PLY radiance_r/g/b). A vertex shows the side its normal points to."""
EXAMPLES = """\
examples:
  isolume export synthetic:engine --out engine.glb
  isolume bake scan.nrrd --out scan.npz && isolume export scan.nrrd --lattice scan.npz \\
      --iso 600 --out scan.ply"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume export``."""

    p.description, p.epilog = DESCRIPTION, EXAMPLES
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    add_volume_options(p, optional=True)
    p.add_argument("--out", required=True,
                   help="FILE.glb (glTF binary, +Y up) or FILE.ply (binary, +Z up)")
    add_light_options(p, "the exported surface")


def run(args: argparse.Namespace) -> int:
    """Export the lit isosurface; returns the exit status."""
    from isolume.app.export_files import SUFFIXES, write_mesh
    from isolume.app.render.images import check_output_path

    out = check_output_path(args.out, SUFFIXES)
    parse_exposure(args.exposure)
    volume = load_volume(args)
    lattice = load_lattice(args.lattice, volume, args.env)
    iso = _served_isovalue(args, volume, lattice)
    shading = _shading(args, volume, lattice)
    mesh = volumes.isosurface(volume, iso, normals=args.normals, flip_normals=args.flip_normals)
    if mesh.empty:
        raise CLIError(f"{volume.source or volume.name}: {mesh.message}; nothing to export")
    if args.flip_normals:  # triangles counter-clockwise seen from the normals' side
        mesh = replace(mesh, faces=np.ascontiguousarray(mesh.faces[:, ::-1]))
    light = _vertex_light(volume, iso, mesh, lattice, shading, args)
    display, exposure = _display_colours(args, mesh, light.radiance)
    extras = _extras(volume, iso, light, exposure, args.tonemap)
    write_mesh(out, mesh, display, light.radiance, extras)
    if light.uncovered:
        print(f"isolume: warning: {light.uncovered:,} of {len(mesh.vertices):,} vertices read "
              "no lit texel of the lattice (none computed there, or all trapped: sealed from "
              "the sky on every path) and are black", file=sys.stderr)
    print(f"wrote {out} ({len(mesh.vertices):,} vertices, {len(mesh.faces):,} triangles, "
          f"{volume.name} at iso {iso:.6g}, {light.source}, exposure {exposure:.3g}, "
          f"tone curve {args.tonemap})")
    return 0


@dataclass(frozen=True)
class Shading:
    """How the vertices are lit, checked before any work.

    Attributes:
        traced: the `BakeConfig` of the global illumination to trace (no lattice), or None.
        albedo: (3,) diffuse reflectance.
        env_rotation: (azimuth, elevation) degrees an SH lattice's environment turns by.
        env_coeffs: (m, 3) environment coefficients of an SH lattice, or None.
    """

    traced: BakeConfig | None
    albedo: tuple[float, float, float]
    env_rotation: tuple[float, float]
    env_coeffs: np.ndarray | None


@dataclass(frozen=True)
class VertexLight:
    """The light of every vertex and where it came from.

    Attributes:
        radiance: (V, 3) linear outgoing radiance (the lighting's irradiance units / sr).
        source: what lit it, for the summary line.
        lighting: the environment and light specs.
        uncovered: vertices whose lookups read no texel a display uses
            (`Lattice.shown`: none computed, or trapped), drawn black.
    """

    radiance: np.ndarray
    source: str
    lighting: str
    uncovered: int


def _shading(args: argparse.Namespace, volume: volumes.Volume, lattice) -> Shading:
    """The checked lighting options: --env and --light only where a lattice can honour
    them (not with an irradiance lattice, whose light is baked; no --light with an SH
    lattice, lit by its environment alone), the traced light's settings without a lattice,
    the albedo (--albedo, else the lattice's or the traced light's), the SH environment."""
    rotation = floats(args.env_rotation, 2, "--env-rotation")
    if lattice is None:
        traced = view_light(args, volume)
        return Shading(traced, traced.albedo, rotation, None)
    if lattice.kind == "irradiance" and (args.env or args.light):
        raise CLIError(f"--env/--light: {args.lattice} holds irradiance baked under its own "
                       f"lighting ({_lighting_text(lattice)}); bake again for other light, "
                       "or leave out --lattice")
    if lattice.kind == "sh" and args.light:
        raise CLIError(f"--light: {args.lattice} holds SH transfer, lit by its environment "
                       "(--env) alone; bake the lights into an irradiance lattice, or leave "
                       "out --lattice")
    if args.albedo is not None:
        albedo = parse_albedo(args.albedo)
    else:
        albedo = lattice.config.albedo if lattice.config is not None else (0.8, 0.8, 0.8)
    env_coeffs = (environment_coefficients(args.env, lattice, args.sh_window)
                  if lattice.kind == "sh" else None)
    return Shading(None, albedo, rotation, env_coeffs)


def _served_isovalue(args: argparse.Namespace, volume: volumes.Volume, lattice) -> float:
    """The isovalue to export (--iso, or the first suggested), checked against the data
    range and the isovalues the lattice serves."""
    iso = isovalue(volume, args.iso)
    check_served(lattice, iso, args.lattice)
    return iso


def _vertex_light(volume: volumes.Volume, iso: float, mesh: volumes.Mesh, lattice,
                  shading: Shading, args: argparse.Namespace) -> VertexLight:
    """The radiance at the mesh's vertices (`app.export_light.surface_radiance`): the
    lattice's light (or the light traced for the surface without one) plus the direct
    light it leaves to the pixels."""
    from isolume.app.export_light import COVERED, coverage, surface_radiance
    from isolume.baking.trace import Scene

    radiance, read, lights = surface_radiance(
        volume, iso, mesh, Scene(mesh.vertices, mesh.faces), lattice, shading.traced,
        shading.albedo, env_coeffs=shading.env_coeffs, env_rotation=shading.env_rotation,
        workers=args.workers, progress=True, spread=args.spread)
    each = "each" if args.spread == "even" else "a texel on average"
    if lattice is None:
        source = f"global illumination traced with {shading.traced.samples} paths {each}"
    elif isinstance(args.lattice, str | os.PathLike):
        source = f"{lattice.kind} lattice {args.lattice}"
    else:  # a Lattice from the Python API names itself
        source = str(args.lattice)
    if lights:
        plural = "" if len(lights) == 1 else "s"
        source += f" + direct light of {len(lights)} light{plural} through shadow rays"
    uncovered = int((coverage(read, np.asarray(mesh.vertices, np.float64)) < COVERED).sum())
    return VertexLight(radiance, source, _lighting_text(read), uncovered)


def _lighting_text(lattice) -> str:
    """The lattice's environment and light specs, one line."""
    config = lattice.config
    return "lighting not recorded" if config is None else config.lighting_text


def _display_colours(args: argparse.Namespace, mesh: volumes.Mesh, radiance: np.ndarray
                     ) -> tuple[np.ndarray, float]:
    """((V, 3) display colours in [0, 1], linear; the exposure): the radiance times
    --exposure (and the automatic exposure of the surface, its vertices weighted by their
    areas) through the tone curve."""
    from isolume.app.export_files import tone, vertex_areas
    from isolume.app.render.exposure import auto_exposure_scale

    exposure = args.exposure
    if not args.no_auto_exposure:
        exposure *= auto_exposure_scale(radiance, np.ones(len(radiance), bool),
                                        weights=vertex_areas(mesh.vertices, mesh.faces))
    return tone(radiance * exposure, args.tonemap), float(exposure)


def _extras(volume: volumes.Volume, iso: float, light: VertexLight, exposure: float,
            tonemap: str) -> dict:
    """What the file says about how its colours were made (one line per value)."""
    return {"volume": volume.source or volume.name, "isovalue": float(iso),
            "light": light.source, "lighting": light.lighting, "exposure": exposure,
            "tonemap": tonemap, "colours": "exposed and tone-mapped display colours",
            "radiance": "linear outgoing radiance, unexposed"}
