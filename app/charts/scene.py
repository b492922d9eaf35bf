"""The GL side of ``isolume chart``: one headless context, renderer, mesh and camera for
every image of a run (`app.render.renderer.SurfaceRenderer`; EGL by default, llvmpipe where
there is no GPU), same mesh, camera and albedo for every image. The images whose error is
measured get the per-pixel lights' direct light traced as ``isolume render`` traces it
(`app.render.traced_light`); the frames that are timed, the viewer's shadow maps."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from isolume.app.charts.lighting import LocalLighting
from isolume.app.charts.metrics import Image

if TYPE_CHECKING:
    import moderngl

    from isolume.app.render.camera import Camera
    from isolume.app.render.glcontext import HeadlessContext
    from isolume.app.render.renderer import SurfaceRenderer
    from isolume.app.render.settings import RenderSettings
    from isolume.baking.lattice import Lattice
    from isolume.volumes import Volume
    from isolume.volumes.mesh import Mesh


class GLScene:
    """One headless context, renderer, mesh and camera for every image of a run."""

    volume: Volume
    camera: Camera
    size: tuple[int, int]
    lighting: LocalLighting
    albedo: float
    env_spec: str
    mesh: Mesh
    gl: HeadlessContext
    ctx: moderngl.Context
    renderer: SurfaceRenderer

    def __init__(self, volume: Volume, iso: float, camera: Camera, size: tuple[int, int],
                 backend: str, lighting: LocalLighting, albedo: float, env_spec: str) -> None:
        from isolume import volumes
        from isolume.app.render.glcontext import create_headless
        from isolume.app.render.renderer import SurfaceRenderer

        self.volume, self.camera, self.size = volume, camera, size
        self.lighting, self.albedo, self.env_spec = lighting, albedo, env_spec
        self.mesh = volumes.isosurface(volume, iso)
        self.gl = create_headless(backend)
        self.ctx = self.gl.ctx
        self.renderer = SurfaceRenderer(self.ctx)
        self.renderer.set_mesh(self.mesh.vertices, self.mesh.normals, self.mesh.faces,
                               iso=self.mesh.iso)
        self.renderer.set_bounds(*volume.box)
        self._lattice = None
        self._scene = None  # the mesh's Embree scene, for the traced direct light
        self._traced_key: tuple | None = None
        self._texel_iso: dict = {}
        self._env: dict = {}

    @property
    def gl_renderer(self) -> str:
        info = self.ctx.info
        return f"{info.get('GL_RENDERER')} ({info.get('GL_VERSION')}, {self.gl.backend})"

    def settings(self, shading: str) -> RenderSettings:
        """`RenderSettings` of `shading`: the run's size and albedo, the local lighting."""
        from isolume.app.render.settings import RenderSettings

        light = self.lighting
        return RenderSettings(size=self.size, shading=shading, albedo=(self.albedo,) * 3,
                              key_dir=light.key_dir, key_irradiance=light.key,
                              head_irradiance=(0.0, 0.0, 0.0), sky_irradiance=light.sky,
                              ground_irradiance=light.ground)

    def use(self, shading: str, lattice: Lattice | None = None) -> None:
        """Upload what `shading` reads: the lattice (with texel isovalues for the
        closest-isovalue lookup) and, for SH, the environment's coefficients."""
        from isolume.app.render.settings import SHADING_MODES

        mode = SHADING_MODES[shading]
        closest = mode.lookup == "closest" and lattice is not None
        key = (id(lattice), closest)
        if self._lattice != key:
            self.renderer.set_lattice(lattice, self._texel_isovalues(lattice) if closest
                                      else None)
            self._lattice = key
        if shading == "sh":
            from isolume.baking.sh import transfer_blocks

            self.renderer.set_environment(self._env_coeffs(int(lattice.meta["sh_order"]),
                                                           transfer_blocks(lattice)))

    def _texel_isovalues(self, lattice) -> np.ndarray:
        from isolume.baking.plan import texel_values

        shape = lattice.geometry.shape
        if shape not in self._texel_iso:
            self._texel_iso[shape] = texel_values(self.volume, lattice.geometry)
        return self._texel_iso[shape]

    def _env_coeffs(self, order: int, blocks: int = 1) -> np.ndarray:
        """`baking.sh.display_coefficients` of the chart's environment (cached)."""
        from isolume.baking import sh
        from isolume.baking.environment import parse_env

        if (order, blocks) not in self._env:
            self._env[order, blocks] = sh.display_coefficients(parse_env(self.env_spec),
                                                               order, blocks)
        return self._env[order, blocks]

    def render(self, shading: str, lattice: Lattice | None = None) -> Image:
        """Draw `shading` (with `lattice` where it reads one) and read it back."""
        self.use(shading, lattice)
        self._trace_direct(shading)
        frame = self.renderer.render(self.camera, self.settings(shading))
        return Image(frame.linear.reshape(-1, 3).astype(np.float64), frame.mask.reshape(-1))

    def _trace_direct(self, shading: str) -> None:
        """Trace the direct light of the per-pixel lights of `shading`'s frame, once per
        lights and lattice start (offset and normals)."""
        from isolume.app.render.traced_light import position_pass, trace_direct_light
        from isolume.baking.trace import Scene

        settings = self.settings(shading)
        lights = self.renderer.direct_lights(settings)
        lattice = self.renderer.lattice
        config = None if lattice is None else lattice.lattice.config
        key = (None if not lights or config is None else
               (lights, config.offset, config.normals, config.flip_normals))
        if key == self._traced_key:
            return
        self._traced_key = key
        if key is None:
            self.renderer.set_traced_light((), None)
            return
        if self._scene is None:
            self._scene = Scene(self.mesh.vertices, self.mesh.faces)
        trace_direct_light(self.renderer, self.camera, settings, self.volume,
                           position_pass(self.renderer, self.camera, settings), self._scene,
                           smooth=config.normals == "smooth")

    def frame_seconds(self, shading: str, lattice: Lattice | None, draws: int,
                      warmup: int = 3) -> np.ndarray:
        """(draws,) wall seconds of single frames (linear pass + tone-mapping pass, ended by
        ``ctx.finish()``, no read-back) after `warmup` untimed ones, the per-pixel lights
        shadowed by the viewer's shadow maps."""
        self.use(shading, lattice)
        self.renderer.set_traced_light((), None)
        self._traced_key = None
        settings = self.settings(shading)
        times = []
        for i in range(warmup + draws):
            began = time.perf_counter()
            targets = self.renderer.draw_hdr(self.camera, settings)
            self.renderer.resolve(targets, settings)
            self.ctx.finish()
            if i >= warmup:
                times.append(time.perf_counter() - began)
        return np.array(times)

    def release(self) -> None:
        self.renderer.release()
        self.gl.release()

