"""Off-screen rendering of a volume's isosurface (EGL or OSMesa), for CLI and tests."""

from __future__ import annotations

import numpy as np

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.glcontext import create_headless
from isolume.app.render.renderer import SurfaceRenderer, framed_camera
from isolume.app.render.settings import SHADING_MODES, Frame, RenderSettings
from isolume.baking.view_texels import LatticeOnFile


def _texel_isovalues(volume: volumes.Volume, lattice, shading: str) -> np.ndarray | None:
    """(Z, Y, X) field values at the lattice's texel centres when `shading` reads them."""
    mode = SHADING_MODES.get(shading)
    if lattice is None or mode is None or mode.lookup != "closest":
        return None
    from isolume.baking.plan import texel_values

    return texel_values(volume, lattice.geometry)


def _visible_points(renderer: SurfaceRenderer, camera: Camera,
                    settings: RenderSettings) -> np.ndarray:
    """(N, 3) world points of the surface under the visible pixels (a position pass)."""
    from dataclasses import replace

    position = renderer.render(camera, replace(settings, shading="position",
                                               auto_exposure=False))
    return position.linear[position.mask]


def _read_texels(renderer: SurfaceRenderer, camera: Camera, settings: RenderSettings,
                 geometry) -> np.ndarray | None:
    """(K,) sorted flat ids of the texels of `geometry` that the picture of `camera` reads
    (`baking.preview.picture_texels`); None (all) for a lookup that reads further than a
    cell's corners (the B-spline's 4³)."""
    from isolume.baking.preview import picture_texels

    mode = SHADING_MODES.get(settings.shading)
    if mode is not None and mode.lookup == "bspline":
        return None
    return picture_texels(geometry, _visible_points(renderer, camera, settings))


def render_volume(
    volume: volumes.Volume,
    iso: float,
    settings: RenderSettings,
    *,
    view: tuple[float, float, float | None] | None = None,
    camera: Camera | None = None,
    backend: str = "auto",
    normals: str = "smooth",
    flip_normals: bool = False,
    lattice=None,
    env_coeffs=None,
    view_light=None,
    workers: int | None = None,
    progress: bool = False,
) -> tuple[Frame, volumes.Mesh]:
    """Extract the isosurface at `iso` and render it in a fresh headless context, seen
    from `camera`, or (None) from the orbit `view` (azimuth, elevation degrees, distance
    in diagonals or None) around the surface's box (`framed_camera`).

    `lattice` (a `baking.Lattice`, a `baking.view_texels.HeldLattice`, or a
    `baking.view_texels.LatticeOnFile` whose texels under the visible pixels are read after
    a position pass) is needed by the lattice shading modes, `env_coeffs`
    ((n², 3) SH coefficients of the environment) by "sh". Without a lattice, `view_light`
    (a `baking.config.BakeConfig`) lights this view instead: a position pass finds the
    visible surface and `app.render.view_gi.view_lattice` traces the texels it reads (`workers`
    threads, `progress` on stderr) on an Embree scene of the mesh, while GL holds no copy of
    the mesh (it is uploaded again for the picture). The shadow map and the fog are fitted
    to the volume's world box; "irradiance_closest" gets the texel isovalues computed from
    `volume` here.

    Returns:
        (frame, mesh): the picture and the mesh that was drawn.
    """
    mesh = volumes.isosurface(volume, iso, normals=normals, flip_normals=flip_normals)
    gl = create_headless(backend)
    try:
        renderer = SurfaceRenderer(gl.ctx)
        renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        renderer.set_bounds(*volume.box)
        camera = camera or framed_camera(volume, iso, view, settings.size)
        if isinstance(lattice, LatticeOnFile):  # read the texels the pixels read
            lattice = lattice.held(_read_texels(renderer, camera, settings, lattice.geometry))
        elif lattice is None and view_light is not None and len(mesh.faces):
            from isolume.app.render.view_gi import view_lattice
            from isolume.baking.trace import Scene

            points = _visible_points(renderer, camera, settings)
            renderer.release_mesh()  # GL's copy and Embree's scene are not held at once
            lattice = view_lattice(volume, view_light, iso, points, camera.eye,
                                   workers=workers, progress=progress,
                                   scene=Scene(mesh.vertices, mesh.faces))
            renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        renderer.set_lattice(lattice, _texel_isovalues(volume, lattice, settings.shading))
        renderer.set_environment(env_coeffs)
        frame = renderer.render(camera, settings)
        renderer.release()
    finally:
        gl.release()
    return frame, mesh
