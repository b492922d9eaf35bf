"""Drawing isosurface meshes with moderngl into a linear HDR target, then to display.

`SurfaceRenderer` owns the GL objects for one context: shader programs (one per shading
mode, compiled on first use), the mesh buffers and the framebuffers. Each frame is drawn
in linear radiance into an RGBA32F target (alpha marks surface pixels), then exposure,
tone curve and sRGB encoding are applied in a full-screen pass. Everything here works the
same in a glfw window and off-screen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import moderngl
import numpy as np

import shaders

from .camera import Camera
from .lattice_gl import LatticeTextures

LOCAL_MODES = {"lambert": 1, "phong": 2, "lambert_hemi": 3, "phong_hemi": 4}
"""Local shading models: name -> SHADING define in ``surface.frag``."""
LATTICE_MODES = {"irradiance": 5, "sh": 6}
"""Modes that read an illumination lattice."""
SHADING_MODES = {**LOCAL_MODES, **LATTICE_MODES}
"""Every user-facing shading mode."""
_DEBUG_MODES = {"position": 9}  # world position in the HDR target (tests, picking)


class RenderError(ValueError):
    """A frame that cannot be drawn as asked (mode without its lattice or environment)."""

TONEMAPS = {"clamp": 0, "reinhard": 1, "aces": 2}


@dataclass(frozen=True)
class RenderSettings:
    """What a frame looks like (not where it is seen from: that is the `Camera`).

    Irradiances are linear RGB at normal incidence; a diffuse surface of albedo a lit by
    E returns radiance a·E/π.

    Attributes:
        size: (width, height) pixels.
        shading: a key of `LOCAL_MODES`.
        exposure: linear multiplier applied before the tone curve.
        tonemap: a key of `TONEMAPS`.
        background: linear RGB shown where there is no surface.
        albedo: diffuse reflectance, linear RGB.
        key_dir: unit vector towards the key light in world space, or None for a light
            fixed to the camera (above-left of the eye).
        key_irradiance, head_irradiance: key light and headlight.
        sky_irradiance, ground_irradiance: hemisphere ambient for normals facing +z / −z.
        shininess, specular: Blinn–Phong exponent and specular albedo (phong modes).
        env_rotation: (azimuth, elevation) degrees of the environment in "sh" mode
            (`baking.sh.rotation_from_az_el`); (0, 0) leaves it as loaded.
    """

    size: tuple[int, int] = (512, 512)
    shading: str = "phong_hemi"
    exposure: float = 1.0
    tonemap: str = "aces"
    background: tuple[float, float, float] = (0.03, 0.035, 0.045)
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    key_dir: tuple[float, float, float] | None = None
    key_irradiance: tuple[float, float, float] = (1.9, 1.85, 1.8)
    head_irradiance: tuple[float, float, float] = (0.5, 0.5, 0.5)
    sky_irradiance: tuple[float, float, float] = (0.7, 0.75, 0.85)
    ground_irradiance: tuple[float, float, float] = (0.25, 0.22, 0.2)
    shininess: float = 40.0
    specular: float = 0.12
    env_rotation: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if self.shading not in SHADING_MODES and self.shading not in _DEBUG_MODES:
            raise ValueError(
                f"unknown shading mode {self.shading!r}; expected one of "
                f"{', '.join(SHADING_MODES)}"
            )
        if self.tonemap not in TONEMAPS:
            raise ValueError(f"unknown tone map {self.tonemap!r}; expected {', '.join(TONEMAPS)}")
        w, h = self.size
        if not (1 <= w <= 16384 and 1 <= h <= 16384):
            raise ValueError(f"image size {w}x{h} must be between 1 and 16384 per side")
        if not self.exposure > 0:
            raise ValueError(f"exposure must be positive, got {self.exposure:g}")


def key_direction(camera: Camera, settings: RenderSettings) -> np.ndarray:
    """(3,) unit vector towards the key light, world space."""
    if settings.key_dir is not None:
        d = np.asarray(settings.key_dir, np.float64)
        return d / np.linalg.norm(d)
    view = camera.view_matrix()[:3, :3]  # rows: right, up, back
    d = view.T @ np.array([-0.45, 0.6, 0.65])  # from above-left of the eye
    return d / np.linalg.norm(d)


@dataclass
class Frame:
    """A rendered image.

    Attributes:
        linear: (H, W, 3) float32 linear radiance (before exposure); 0 off the surface.
        srgb: (H, W, 3) uint8 display image (exposure, tone curve, sRGB).
        mask: (H, W) bool, True on surface pixels.
    """

    linear: np.ndarray
    srgb: np.ndarray
    mask: np.ndarray


@dataclass
class _Targets:
    size: tuple[int, int]
    hdr: moderngl.Framebuffer
    hdr_color: moderngl.Texture
    ldr: moderngl.Framebuffer
    objects: list = field(default_factory=list)

    def release(self) -> None:
        for obj in self.objects:
            obj.release()


class SurfaceRenderer:
    """Renders one isosurface mesh with the shading modes of this module."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self._programs: dict[tuple[str, tuple], moderngl.Program] = {}
        self._mesh_objects: list = []
        self._vao: moderngl.VertexArray | None = None
        self._triangles = 0
        self._targets: _Targets | None = None
        self.lattice: LatticeTextures | None = None
        self._env_coeffs: np.ndarray | None = None
        # Framebuffer 0 is always valid to bind; parking on it before freeing our targets
        # keeps moderngl from re-binding a deleted framebuffer (GL_INVALID_OPERATION).
        self._default_fbo = ctx.screen or ctx.detect_framebuffer(0)

    # -- resources ---------------------------------------------------------------------
    def _program(self, kind: str, defines: tuple) -> moderngl.Program:
        key = (kind, defines)
        if key not in self._programs:
            d = dict(defines)
            if kind == "tonemap":
                vs, fs = shaders.source("fullscreen.vert"), shaders.source("tonemap.frag", d)
            else:
                vs, fs = shaders.source("surface.vert"), shaders.source("surface.frag", d)
            self._programs[key] = self.ctx.program(vertex_shader=vs, fragment_shader=fs)
        return self._programs[key]

    def set_mesh(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
        """Upload a mesh: (V, 3) float32 world positions, (V, 3) normals, (F, 3) indices."""
        for obj in self._mesh_objects:
            obj.release()
        self._mesh_objects, self._vao, self._triangles = [], None, len(faces)
        if len(faces) == 0:
            return
        interleaved = np.hstack([vertices, normals]).astype(np.float32)
        vbo = self.ctx.buffer(interleaved.tobytes())
        ibo = self.ctx.buffer(np.ascontiguousarray(faces, np.uint32).tobytes())
        self._mesh_objects = [vbo, ibo]
        self._vertex_buffers = (vbo, ibo)

    def set_lattice(self, lattice) -> None:
        """Upload an illumination lattice (`baking.Lattice`) for the lattice modes; None
        removes it."""
        if self.lattice is not None:
            self.lattice.release()
            self.lattice = None
        if lattice is not None:
            self.lattice = LatticeTextures(self.ctx, lattice)

    def set_environment(self, coeffs: np.ndarray | None) -> None:
        """(n², 3) SH coefficients ℓ of the environment radiance for "sh" mode (as projected
        by `baking.sh.project_environment`; rotated every frame by `env_rotation`)."""
        self._env_coeffs = None if coeffs is None else np.asarray(coeffs, np.float64)

    def _sh_light(self, settings: RenderSettings) -> np.ndarray:
        """(n², 3) environment coefficients rotated by the settings' env_rotation."""
        from baking import sh

        if self._env_coeffs is None:
            raise RenderError("shading 'sh' needs an environment (--env SPEC)")
        order = self.lattice.sh_order
        coeffs = self._env_coeffs[: order * order]
        if coeffs.shape[0] < order * order:
            raise RenderError(f"environment has {coeffs.shape[0]} SH coefficients, the lattice "
                             f"needs {order * order}")
        r = sh.rotation_from_az_el(*settings.env_rotation)
        return sh.rotation(r, order) @ coeffs

    def _mesh_vao(self, program: moderngl.Program) -> moderngl.VertexArray | None:
        if not self._mesh_objects:
            return None
        vbo, ibo = self._vertex_buffers
        # a shader may not use the normal (the position pass): skip those 12 bytes then
        layout = ((vbo, "3f 3f", "in_position", "in_normal") if "in_normal" in program
                  else (vbo, "3f 12x", "in_position"))
        vao = self.ctx.vertex_array(program, [layout], index_buffer=ibo, index_element_size=4)
        self._mesh_objects.append(vao)
        return vao

    def _ensure_targets(self, size: tuple[int, int]) -> _Targets:
        if self._targets is not None and self._targets.size == size:
            return self._targets
        if self._targets is not None:
            self._default_fbo.use()
            self._targets.release()
        ctx = self.ctx
        color = ctx.texture(size, 4, dtype="f4")
        depth = ctx.depth_renderbuffer(size)
        hdr = ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        ldr_color = ctx.texture(size, 4, dtype="f1")
        ldr = ctx.framebuffer(color_attachments=[ldr_color])
        self._targets = _Targets(size, hdr, color, ldr, [hdr, color, depth, ldr, ldr_color])
        return self._targets

    def release(self) -> None:
        """Free every GL object this renderer made."""
        for obj in self._mesh_objects:
            obj.release()
        self.set_lattice(None)
        if self._targets is not None:
            self._default_fbo.use()
            self._targets.release()
        for prog in self._programs.values():
            prog.release()

    # -- drawing -----------------------------------------------------------------------
    def _set_uniforms(self, prog: moderngl.Program, camera: Camera, s: RenderSettings) -> None:
        w, h = s.size
        values = {
            "u_view_proj": camera.view_proj(w / h).T.astype("f4").tobytes(),
            "u_eye": tuple(camera.eye),
            "u_albedo": s.albedo,
            "u_key_dir": tuple(key_direction(camera, s)),
            "u_key_irradiance": s.key_irradiance,
            "u_head_irradiance": s.head_irradiance,
            "u_sky_irradiance": s.sky_irradiance,
            "u_ground_irradiance": s.ground_irradiance,
            "u_shininess": s.shininess,
            "u_specular": s.specular,
        }
        for name, value in values.items():
            if name not in prog:
                continue
            if isinstance(value, bytes):
                prog[name].write(value)
            else:
                prog[name].value = value

    def _surface_program(self, shading: str) -> moderngl.Program:
        """The compiled surface program for `shading` (checks the lattice it needs)."""
        defines: tuple = (("SHADING", {**SHADING_MODES, **_DEBUG_MODES}[shading]),)
        if shading in LATTICE_MODES:
            if self.lattice is None:
                raise RenderError(f"shading {shading!r} needs a lattice (--lattice FILE)")
            want = "sh" if shading == "sh" else "irradiance"
            if self.lattice.kind != want:
                raise RenderError(f"shading {shading!r} needs an {want} lattice, this one holds "
                                  f"{self.lattice.kind}")
            if shading == "sh":
                defines += self.lattice.sh_defines()
        return self._program("surface", defines)

    def draw_hdr(self, camera: Camera, settings: RenderSettings) -> _Targets:
        """Draw the mesh in linear radiance into the HDR target (alpha 1 on the surface)."""
        targets = self._ensure_targets(settings.size)
        targets.hdr.use()
        self.ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        if self._triangles:
            prog = self._surface_program(settings.shading)
            self._set_uniforms(prog, camera, settings)
            if settings.shading in LATTICE_MODES:
                self.lattice.bind(prog)
            if settings.shading == "sh":
                light = self.lattice.light_uniform(self._sh_light(settings))
                prog["u_light"].write(light.tobytes())
            vao = self._mesh_vao(prog)
            self.ctx.enable(moderngl.DEPTH_TEST)
            self.ctx.disable(moderngl.CULL_FACE)
            vao.render(moderngl.TRIANGLES)
            self._mesh_objects.remove(vao)
            vao.release()
        return targets

    def resolve(self, targets: _Targets, settings: RenderSettings, fbo=None) -> None:
        """Tone-map the HDR target into `fbo` (default: the internal 8-bit target)."""
        prog = self._program("tonemap", (("TONEMAP", TONEMAPS[settings.tonemap]),))
        (fbo or targets.ldr).use()
        self.ctx.disable(moderngl.DEPTH_TEST)
        targets.hdr_color.use(location=0)
        prog["u_hdr"].value = 0
        prog["u_exposure"].value = settings.exposure
        prog["u_background"].value = settings.background
        vao = self.ctx.vertex_array(prog, [])
        vao.render(moderngl.TRIANGLES, vertices=3)
        vao.release()

    def render(self, camera: Camera, settings: RenderSettings) -> Frame:
        """Draw one frame off-screen and read it back (rows top to bottom)."""
        targets = self.draw_hdr(camera, settings)
        self.resolve(targets, settings)
        w, h = settings.size
        hdr = np.frombuffer(targets.hdr.read(components=4, dtype="f4"), np.float32)
        hdr = hdr.reshape(h, w, 4)[::-1]
        ldr = np.frombuffer(targets.ldr.read(components=3), np.uint8).reshape(h, w, 3)[::-1]
        mask = hdr[..., 3] > 0
        return Frame(np.ascontiguousarray(hdr[..., :3]), np.ascontiguousarray(ldr), mask)


def default_camera(volume, view: tuple[float, float, float | None] | None = None) -> Camera:
    """Orbit camera around the centre of `volume`'s sample box (distance in diagonals)."""
    lo, hi = volume.sample_box
    az, el, dist = view if view is not None else (30.0, 30.0, None)
    return Camera(
        azimuth=az, elevation=el, distance=1.8 if dist is None else dist,
        target=tuple((lo + hi) / 2), scale=volume.diagonal,
    )
