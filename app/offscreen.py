"""Off-screen rendering of a volume's isosurface (EGL or OSMesa), for CLI and tests."""

from __future__ import annotations

import volumes

from .glcontext import create_headless
from .render import Frame, RenderSettings, SurfaceRenderer, default_camera


def render_volume(
    volume: volumes.Volume,
    iso: float,
    settings: RenderSettings,
    *,
    view: tuple[float, float, float | None] | None = None,
    backend: str = "auto",
    normals: str = "smooth",
    flip_normals: bool = False,
    lattice=None,
    env_coeffs=None,
) -> tuple[Frame, volumes.Mesh]:
    """Extract the isosurface at `iso` and render it in a fresh headless context.

    `lattice` (a `baking.Lattice`) is needed by the lattice shading modes, `env_coeffs`
    ((n², 3) SH coefficients of the environment) by "sh".

    Returns:
        (frame, mesh): the picture and the mesh that was drawn.
    """
    mesh = volumes.isosurface(volume, iso, normals=normals, flip_normals=flip_normals)
    gl = create_headless(backend)
    try:
        renderer = SurfaceRenderer(gl.ctx)
        renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces)
        renderer.set_lattice(lattice)
        renderer.set_environment(env_coeffs)
        frame = renderer.render(default_camera(volume, view), settings)
        renderer.release()
    finally:
        gl.release()
    return frame, mesh
