"""Off-screen rendering of a volume's isosurface (EGL or OSMesa), for CLI and tests."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.glcontext import HeadlessContext, create_headless
from isolume.app.render.renderer import SurfaceRenderer, framed_camera
from isolume.app.render.settings import SHADING_MODES, Frame, RenderSettings
from isolume.app.render.traced_light import position_pass, trace_direct_light
from isolume.baking.view_texels import LatticeOnFile
from isolume.volumes import cores

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice


def _texel_isovalues(volume: volumes.Volume, lattice, shading: str) -> np.ndarray | None:
    """(Z, Y, X) field values at the lattice's texel centres when `shading` reads them."""
    mode = SHADING_MODES.get(shading)
    if lattice is None or mode is None or mode.lookup != "closest":
        return None
    from isolume.baking.plan import texel_values

    return texel_values(volume, lattice.geometry)


def _read_texels(settings: RenderSettings, geometry, points: np.ndarray) -> np.ndarray | None:
    """(K,) sorted flat ids of the texels of `geometry` that a picture whose visible
    surface points are `points` (N, 3) reads (`baking.preview.picture_texels`); None (all)
    for a lookup that reads further than a cell's corners (the B-spline's 4³)."""
    from isolume.baking.preview import picture_texels

    mode = SHADING_MODES.get(settings.shading)
    if mode is not None and mode.lookup == "bspline":
        return None
    return picture_texels(geometry, points)


def _warn_unbaked(lattice: HeldLattice, source: object) -> None:
    """A warning on stderr where texels the picture reads have no paths in the lattice
    file `source` yet (an unfinished bake: those pixels take their neighbours' light, or
    local shading where none has any)."""
    if lattice.unbaked:
        read = lattice.unbaked + len(lattice.texels) - lattice.filled
        print(f"isolume: warning: {source} is unfinished: {lattice.unbaked:,} of the "
              f"{read:,} texels this picture reads have no paths yet (drawn from their "
              "neighbours' light, or local shading); run its bake again to finish it",
              file=sys.stderr)


class Reuse:
    """What consecutive renders in one process keep (the Python API's session): one
    headless context per GL back end, made current again on the thread that renders, and
    the last isosurface (the same volume object, isovalue and normals give the same
    mesh). Call `release` when done."""

    def __init__(self) -> None:
        self._contexts: dict[str, HeadlessContext] = {}
        self._mesh: tuple[tuple, volumes.Mesh] | None = None

    def context(self, backend: str) -> HeadlessContext:
        """The context of `backend` ("auto", "egl", "osmesa"), created on first use."""
        gl = self._contexts.get(backend)
        if gl is None:
            gl = self._contexts[backend] = create_headless(backend)
        else:
            gl.make_current()
        return gl

    def mesh(self, volume: volumes.Volume, iso: float, normals: str,
             flip_normals: bool) -> volumes.Mesh:
        """The isosurface of `volume` at `iso` (`volumes.isosurface`), kept for the next
        call with the same arguments."""
        key = (volume, float(iso), normals, bool(flip_normals))
        if self._mesh is None or self._mesh[0] != key:
            mesh = volumes.isosurface(volume, iso, normals=normals, flip_normals=flip_normals)
            self._mesh = (key, mesh)
        return self._mesh[1]

    def release(self) -> None:
        """Free the contexts and the kept mesh."""
        for gl in self._contexts.values():
            gl.release()
        self._contexts.clear()
        self._mesh = None


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
    lattice: Lattice | HeldLattice | LatticeOnFile | None = None,
    env_coeffs: np.ndarray | None = None,
    view_light: BakeConfig | None = None,
    view_spread: str = "noise",
    shadows: str = "traced",
    workers: int | None = None,
    progress: bool = False,
    reuse: Reuse | None = None,
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
    threads, `progress` on stderr, the paths spread as `view_spread` says) on an Embree
    scene of the mesh, while GL holds no copy of the mesh (it is uploaded again for the
    picture). The shadow map and the fog are fitted
    to the volume's world box; "irradiance_closest" gets the texel isovalues computed from
    `volume` here. The lights a lattice leaves to the pixels get, with `shadows` "traced",
    the reference's own estimate of their direct light at each pixel, traced on an Embree
    scene of the mesh (`app.render.traced_light`), or with "map" the shadow atlas's, as in
    the viewer. `reuse` keeps the context and the mesh for the next call (`Reuse`).

    Returns:
        (frame, mesh): the picture and the mesh that was drawn.
    """
    from isolume.baking.trace import Scene

    cores.stage("surface")
    if reuse is not None:
        mesh = reuse.mesh(volume, iso, normals, flip_normals)
    else:
        mesh = volumes.isosurface(volume, iso, normals=normals, flip_normals=flip_normals)
    cores.stage("framing")
    gl = reuse.context(backend) if reuse is not None else create_headless(backend)
    try:
        renderer = SurfaceRenderer(gl.ctx)
        renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        renderer.set_bounds(*volume.box)
        camera = camera or framed_camera(volume, iso, view, settings.size)
        seen, scene = None, None
        if isinstance(lattice, LatticeOnFile):  # read the texels the pixels read
            seen = position_pass(renderer, camera, settings)
            source = lattice.file.path
            lattice = lattice.held(_read_texels(settings, lattice.geometry, seen[0]),
                                  fill=True)
            _warn_unbaked(lattice, source)
        elif lattice is None and view_light is not None and len(mesh.faces):
            from isolume.app.render.view_gi import view_lattice

            cores.stage("seen surface")
            seen = position_pass(renderer, camera, settings)
            renderer.release_mesh()  # GL's copy and Embree's scene are not held at once
            cores.stage("level scenes")
            scene = Scene(mesh.vertices, mesh.faces)
            lattice = view_lattice(volume, view_light, iso, seen[0], camera.eye,
                                   workers=workers, progress=progress, scene=scene,
                                   spread=view_spread)
        renderer.set_lattice(lattice, _texel_isovalues(volume, lattice, settings.shading))
        if shadows == "traced" and renderer.direct_lights(settings) and len(mesh.faces):
            if seen is None:
                seen = position_pass(renderer, camera, settings)
            if scene is None:
                renderer.release_mesh()
                cores.stage("level scenes")
                scene = Scene(mesh.vertices, mesh.faces)
            cores.stage("tracing")
            trace_direct_light(renderer, camera, settings, volume, seen, scene,
                               smooth=normals == "smooth", workers=workers)
        if scene is not None:
            del scene
            renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        renderer.set_environment(env_coeffs)
        cores.stage("draw")
        with cores.timed_item("gl"):  # parallel inside: Mesa's llvmpipe threads
            frame = renderer.render(camera, settings)
        renderer.release()
    finally:
        if reuse is None:
            gl.release()
    return frame, mesh
