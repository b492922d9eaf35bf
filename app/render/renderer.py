"""Drawing isosurface meshes with moderngl into a linear HDR target, then to display.

`SurfaceRenderer` owns the GL objects for one context: shader programs (one per shading
mode, compiled on first use), the mesh buffers, the render targets (`passes.Targets`) and
the shadow maps (`shadows.ShadowMaps`). Each frame is drawn in linear radiance into an
RGBA32F target (alpha marks surface pixels), then exposure, tone curve and sRGB encoding
are applied in a full-screen pass. The irradiance lattice modes and the per-pixel lights
are shaded deferred: the mesh pass writes a G-buffer (``gbuffer.glsl``) and one
full-screen pass shades each pixel once (``deferred.frag``), which on llvmpipe costs a
fraction of shading the many partly covered 4×4 blocks of a dense mesh's tiny triangles.
Everything here works the same in a glfw window and off-screen.

The shading modes and what a frame looks like are `app.render.settings`'s; the automatic
exposure is `app.render.exposure`'s.

The irradiance lattice modes add, per pixel, the direct light of the point and directional
lights and the sky's sun of a lattice baked with direct light "pixels"
(`lights.lattice_direct_lights`, or `RenderSettings.direct_lights`): shadow-mapped from
one linear-depth atlas of tiles, the sun's penumbra from its angular radius
(``direct.glsl``). So does ``sh`` for such a lattice (a split transfer): its sun, turned
with the environment (`lights.rotated_lights`), over the transfer shown under the turned
sky without its sun (direct block) and the whole turned sky (indirect block).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import moderngl
import numpy as np
import numpy.typing as npt

from isolume import shaders
from isolume.app.render.camera import Camera, frame_points
from isolume.app.render.exposure import auto_exposure_scale
from isolume.app.render.lattice_gl import MAX_TEXTURE_UNITS, LatticeTextures
from isolume.app.render.lights import (
    direct_sum,
    key_direction,
    lattice_direct_lights,
    lattice_start_offset,
    occlusion_sky,
    rotated_lights,
    unbaked_hemisphere,
)
from isolume.app.render.passes import GBUFFER_UNIT, Targets, pixel_rays
from isolume.app.render.settings import (
    MAX_DIRECT_LIGHTS,
    TONEMAPS,
    Frame,
    RenderError,
    RenderSettings,
    shading_mode,
)
from isolume.app.render.shadows import (
    DIRECT_BIAS_TEXELS,
    DIRECT_UNITS,
    SHADOW_BIAS_TEXELS,
    ShadowMaps,
    active_parts,
    direct_uniforms,
)

if TYPE_CHECKING:
    from isolume.app.render.settings import DirectLight
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice
    from isolume.volumes import Volume

SeenHook = Callable[[tuple[np.ndarray, np.ndarray]], None]
"""Called by `SurfaceRenderer.draw_hdr` with a frame's visible surface: ((N, 3) world points,
(H, W) mask of their pixels), between its mesh pass and its lights."""
VERTEX_BYTES = 24
"""Bytes per vertex in the mesh's vertex buffer: position and normal, float32 xyz each."""
VERTEX_CHUNK = 1 << 20
"""Vertices interleaved and written to the vertex buffer at a time (24 MiB)."""


@dataclass(frozen=True)
class TracedLight:
    """The per-pixel lights' direct light traced for a frame size
    (`SurfaceRenderer.set_traced_light`): the lights, the size (W, H) and the GL texture
    array of their factors (one float layer per light)."""

    lights: tuple[DirectLight, ...]
    size: tuple[int, int]
    texture: moderngl.TextureArray


class SurfaceRenderer:
    """Renders one isosurface mesh with the shading modes of `app.render.settings`."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self._programs: dict[tuple[str, tuple], moderngl.Program] = {}
        self._mesh_objects: list = []
        self._triangles = 0
        self._mesh_generation = 0
        self._mesh_box: tuple[np.ndarray, np.ndarray] | None = None
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._iso: float | None = None
        self._targets: Targets | None = None
        self._lattice_lights: tuple[DirectLight, ...] = ()
        self._direct_offset = 0.0
        self._unbaked: tuple[tuple[float, ...], tuple[float, ...]] | None = None
        self._traced: TracedLight | None = None
        self.lattice: LatticeTextures | None = None
        self._env_coeffs: np.ndarray | None = None
        # Framebuffer 0 is always valid to bind; parking on it before freeing our targets
        # keeps moderngl from re-binding a deleted framebuffer (GL_INVALID_OPERATION).
        self._default_fbo = ctx.screen or ctx.detect_framebuffer(0)
        self._shadows = ShadowMaps(ctx, self._program, self._draw_mesh, self._default_fbo)

    # -- resources ---------------------------------------------------------------------
    def _program(self, kind: str, defines: tuple) -> moderngl.Program:
        key = (kind, defines)
        if key not in self._programs:
            d = dict(defines)
            if kind == "tonemap":
                vs, fs = shaders.source("fullscreen.vert"), shaders.source("tonemap.frag", d)
            elif kind == "shadow":
                vs, fs = shaders.source("shadow.vert"), shaders.source("shadow.frag")
            elif kind == "depth":
                vs, fs = shaders.source("depth.vert"), shaders.source("depth.frag")
            elif kind == "deferred":
                vs, fs = shaders.source("fullscreen.vert"), shaders.source("deferred.frag", d)
            else:
                vs, fs = shaders.source("surface.vert"), shaders.source("surface.frag", d)
            self._programs[key] = self.ctx.program(vertex_shader=vs, fragment_shader=fs)
        return self._programs[key]

    def set_mesh(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                 iso: float | None = None) -> None:
        """Upload a mesh: (V, 3) float32 world positions, (V, 3) normals, (F, 3) indices;
        `iso` is the isovalue it was extracted at (needed by "irradiance_closest"). The
        vertex buffer is filled `VERTEX_CHUNK` vertices at a time (no interleaved copy of
        the whole mesh)."""
        self.release_mesh()
        self._iso = None if iso is None else float(iso)
        if len(faces) == 0:
            return
        self._triangles = len(faces)
        self._mesh_box = (vertices.min(axis=0).astype(np.float64),
                          vertices.max(axis=0).astype(np.float64))
        vbo = self.ctx.buffer(reserve=len(vertices) * VERTEX_BYTES)
        for lo in range(0, len(vertices), VERTEX_CHUNK):
            hi = min(lo + VERTEX_CHUNK, len(vertices))
            chunk = np.hstack([vertices[lo:hi], normals[lo:hi]]).astype(np.float32, copy=False)
            vbo.write(chunk, offset=lo * VERTEX_BYTES)
        ibo = self.ctx.buffer(np.ascontiguousarray(faces, np.uint32))
        self._mesh_objects = [vbo, ibo]
        self._vertex_buffers = (vbo, ibo)

    def release_mesh(self) -> None:
        """Free the mesh's GL buffers (the renderer then draws no surface until the next
        `set_mesh`)."""
        for obj in self._mesh_objects:
            obj.release()
        self._mesh_objects, self._triangles, self._mesh_box = [], 0, None
        self._mesh_generation += 1

    def set_bounds(self, lo: npt.ArrayLike | None, hi: npt.ArrayLike | None) -> None:
        """Scene box (lo, hi), each (3,) world xyz, usually the volume's `box`: the shadow
        map is fitted to its bounding sphere and fog starts at that sphere's near side and
        is measured in its diagonal. Until set (or after `set_bounds(None, None)`), the
        mesh's own bounding box is used, which changes with the isovalue."""
        self._bounds = None if lo is None else (np.asarray(lo, np.float64),
                                                np.asarray(hi, np.float64))

    def scene_sphere(self) -> tuple[np.ndarray, float]:
        """(centre (3,), radius) world units of the sphere around the scene box."""
        lo, hi = self._bounds if self._bounds is not None else self._mesh_box
        return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-9)

    def set_lattice(self, lattice: Lattice | HeldLattice | None,
                    texel_isovalues: np.ndarray | None = None) -> None:
        """Upload an illumination lattice (`baking.Lattice`) for the lattice modes; None
        removes it. `texel_isovalues` (Z, Y, X): the field value at each texel centre
        (`baking.plan.texel_values(volume, lattice.geometry)`), needed by
        "irradiance_closest"."""
        if self.lattice is not None:
            self.lattice.release()
            self.lattice = None
        self._lattice_lights = lattice_direct_lights(lattice)
        self._direct_offset = lattice_start_offset(lattice)
        self._unbaked = unbaked_hemisphere(lattice)
        if lattice is not None:
            self.lattice = LatticeTextures(self.ctx, lattice, texel_isovalues)

    def set_traced_light(self, lights: tuple[DirectLight, ...], seen: np.ndarray | None
                         ) -> None:
        """Light the per-pixel `lights` by traced rays instead of the shadow atlas:
        `seen` (H, W, L) float32 factor of each light at each pixel (the cosine-weighted
        fraction seen, `baking.shadow_rays.light_factors`), rows top to bottom, for
        frames of W×H pixels whose per-pixel lights are `lights` (others keep the atlas);
        None: the atlas for every frame."""
        if self._traced is not None:
            self._traced.texture.release()
            self._traced = None
        if seen is None:
            return
        h, w, layers = seen.shape
        if layers != len(lights) or not 0 < layers <= MAX_DIRECT_LIGHTS:
            raise ValueError(f"traced light of {layers} lights for {len(lights)} lights")
        data = np.ascontiguousarray(np.asarray(seen, np.float32)[::-1].transpose(2, 0, 1))
        texture = self.ctx.texture_array((w, h, layers), 1, data.tobytes(), dtype="f4")
        texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._traced = TracedLight(tuple(lights), (w, h), texture)

    def _traced_for(self, settings: RenderSettings) -> TracedLight | None:
        """The traced light that a frame of `settings` reads, if its lights and size are
        the ones traced."""
        t = self._traced
        if t is None or t.size != tuple(settings.size):
            return None
        return t if t.lights == tuple(self.direct_lights(settings)) else None

    def set_environment(self, coeffs: np.ndarray | None) -> None:
        """(n², 3) SH coefficients ℓ of the environment radiance for "sh" mode (as projected
        by `baking.sh.project_environment`; rotated every frame by `env_rotation`)."""
        self._env_coeffs = None if coeffs is None else np.asarray(coeffs, np.float64)

    def _sh_light(self, settings: RenderSettings) -> np.ndarray:
        """(m, 3) environment coefficients rotated by the settings' env_rotation: n² of
        them, or for a split transfer the sun-free sky's n² then the whole sky's n²
        (`baking.sh.display_coefficients`), each block rotated alike."""
        from isolume.baking import sh

        order = self.lattice.sh_order
        blocks = self.lattice.sh_coefficients // (order * order)
        coeffs = self._env_coeffs[: blocks * order * order]
        turn = sh.rotation(sh.rotation_from_az_el(*settings.env_rotation), order)
        return np.concatenate([turn @ block for block in np.split(coeffs, blocks)])

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

    def _draw_mesh(self, program: moderngl.Program) -> None:
        """Draw the mesh's triangles with `program` (depth test on, both faces)."""
        vao = self._mesh_vao(program)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        vao.render(moderngl.TRIANGLES)
        self._mesh_objects.remove(vao)
        vao.release()

    def _ensure_targets(self, size: tuple[int, int]) -> Targets:
        if self._targets is not None and self._targets.size == size:
            return self._targets
        if self._targets is not None:
            self._default_fbo.use()
            self._targets.release()
        self._targets = Targets.new(self.ctx, size)
        return self._targets

    def release(self) -> None:
        """Free every GL object this renderer made."""
        for obj in self._mesh_objects:
            obj.release()
        self.set_lattice(None)
        self.set_traced_light((), None)
        self._default_fbo.use()
        if self._targets is not None:
            self._targets.release()
        self._shadows.release()
        for prog in self._programs.values():
            prog.release()

    # -- modes -------------------------------------------------------------------------
    def check_mode(self, shading: str) -> None:
        """Raise RenderError unless `shading` can be drawn with what has been set (its
        lattice, environment, texel isovalues and mesh isovalue)."""
        mode = shading_mode(shading)
        if mode.lattice is None:
            return
        if self.lattice is None:
            raise RenderError(f"shading {shading!r} needs a lattice (--lattice FILE)")
        want = mode.lattice_kind
        if self.lattice.kind != want:
            raise RenderError(f"shading {shading!r} needs an {want} lattice, this one holds "
                              f"{self.lattice.kind}")
        if mode.lattice == "occlusion":
            occlusion_sky(self.lattice.lattice)
        if mode.lookup == "closest" and (self.lattice.texel_iso is None or self._iso is None):
            raise RenderError(f"shading {shading!r} needs the texel isovalues "
                              "(set_lattice(..., texel_isovalues=...)) and the mesh's "
                              "isovalue (set_mesh(..., iso=...))")
        if shading == "sh":
            self._check_environment()

    def _check_environment(self) -> None:
        if self._env_coeffs is None:
            raise RenderError("shading 'sh' needs an environment (--env SPEC)")
        order = self.lattice.sh_order
        if self.lattice.sh_coefficients > order * order:  # split: sun-free sky, whole sky
            if self._env_coeffs.shape[0] != self.lattice.sh_coefficients:
                raise RenderError(
                    f"environment has {self._env_coeffs.shape[0]} SH coefficients; this "
                    f"lattice splits its transfer and needs {2 * order * order}: the sky "
                    "without its sun, then the whole sky (baking.sh.display_coefficients)")
        elif self._env_coeffs.shape[0] < order * order:
            raise RenderError(f"environment has {self._env_coeffs.shape[0]} SH coefficients, "
                              f"the lattice needs {order * order}")

    @property
    def lattice_lights(self) -> tuple[DirectLight, ...]:
        """The lights the lattice shown leaves to the pixels (`lattice_direct_lights`)."""
        return self._lattice_lights

    def direct_lights(self, settings: RenderSettings) -> tuple[DirectLight, ...]:
        """The lights `settings` shades per pixel: in the irradiance lattice modes the
        settings' own or the lattice's (`RenderSettings.direct_lights`); in "sh" mode the
        sun of a split lattice, turned with the environment (`env_rotation`); else none."""
        mode = shading_mode(settings.shading)
        if mode.lattice == "sh" and self._lattice_lights:
            return rotated_lights(self._lattice_lights, settings.env_rotation)
        if mode.lattice != "irradiance":
            return ()
        if settings.direct_lights is not None:
            return settings.direct_lights
        return self._lattice_lights

    def _lattice_defines(self, settings: RenderSettings) -> tuple:
        """The defines the surface and the deferred program share: the mode's, the SH
        sum's, FACING (the side-aware lookup, for a lattice with known facings),
        DEFERRED (`_lattice_deferred`) and DIRECT (per-pixel lights)."""
        defines = shading_mode(settings.shading).defines()
        if settings.shading == "sh":
            defines += self.lattice.sh_defines()
        if shading_mode(settings.shading).lattice is not None:
            defines += self.lattice.facing_defines()
        defines += (("DEFERRED", int(self._lattice_deferred(settings))),)
        if self.direct_lights(settings):
            defines += (("DIRECT", 1),)
            if self._traced_for(settings) is not None:
                defines += (("TRACED", 1),)
        return defines

    def _surface_program(self, settings: RenderSettings) -> moderngl.Program:
        """The compiled surface program for the settings' mode (checks what it needs)."""
        self.check_mode(settings.shading)
        return self._program("surface", self._lattice_defines(settings))

    def _lattice_deferred(self, settings: RenderSettings) -> bool:
        """Whether the settings' lattice is read in `_deferred_pass` (``surface.frag``):
        every lattice mode whose textures fit one pass beside the G-buffer and the shadow
        atlas (GL 3.3's 16 texture units; only SH transfer of high orders does not)."""
        mode = shading_mode(settings.shading)
        if mode.lattice is None:
            return False
        atlas = (0 if not self.direct_lights(settings) else
                 1 if self._traced_for(settings) is not None else len(DIRECT_UNITS))
        return self.lattice.units + 1 + atlas <= MAX_TEXTURE_UNITS  # + the G-buffer

    def _deferred(self, settings: RenderSettings) -> bool:
        """Whether the settings' frame has a `_deferred_pass`: a deferred lattice, or
        per-pixel lights."""
        return self._lattice_deferred(settings) or bool(self.direct_lights(settings))

    # -- drawing -----------------------------------------------------------------------
    def _deferred_pass(self, targets: Targets, camera: Camera, settings: RenderSettings
                       ) -> None:
        """Add what ``deferred.frag`` shades from the G-buffer the surface pass left: the
        lattice's radiance (`_lattice_deferred`) and the per-pixel lights' direct light
        (the shadow atlas drawn first if the mesh, lights or scene changed); one
        full-screen pass, blending ONE, ONE."""
        mode = shading_mode(settings.shading)
        lights = self.direct_lights(settings)
        defines = self._lattice_defines(settings)
        if lights:
            defines += (("DIRECT_SUM(p, n, f)", direct_sum(lights)),)
        prog = self._program("deferred", defines)
        self._set_uniforms(prog, self._uniforms(camera, settings))
        if self._lattice_deferred(settings) and mode.lattice == "sh":
            self._bind_sh(prog, settings)
        elif self._lattice_deferred(settings):
            self.lattice.bind(prog)
        if mode.lattice == "occlusion":
            sky = occlusion_sky(self.lattice.lattice)
            self._set_uniforms(prog, {"u_sky_radiance": tuple(sky)})  # "ao" reads it
        if lights:
            self._bind_direct(prog, lights, settings)
        targets.g_surface.use(location=GBUFFER_UNIT)
        self._set_uniforms(prog, {"u_gbuffer": GBUFFER_UNIT,
                                  **pixel_rays(camera, settings.size)})
        targets.hdr.use()
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.ONE, moderngl.ONE
        vao = self.ctx.vertex_array(prog, [])
        vao.render(moderngl.TRIANGLES, vertices=3)
        vao.release()
        self.ctx.disable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.DEFAULT_BLENDING

    def _bind_direct(self, prog: moderngl.Program, lights: tuple,
                     settings: RenderSettings) -> None:
        """Draw (if needed) and bind the per-pixel lights' shadow atlas, or their traced
        light (`set_traced_light`), and uniforms."""
        traced = self._traced_for(settings)
        if traced is not None:
            traced.texture.use(location=DIRECT_UNITS[0])
            no_tiles = direct_uniforms(lights, [], [], [], [], [])
            self._set_uniforms(prog, {**active_parts(prog, no_tiles),
                                      "u_traced": DIRECT_UNITS[0],
                                      "u_direct_offset": self._direct_offset})
            return
        atlas = self._shadows.atlas(lights, settings.shadow_resolution, self.scene_sphere(),
                                    self._mesh_generation)
        shadow_unit, raw_unit = DIRECT_UNITS
        atlas.depth.use(location=shadow_unit)
        atlas.raw.use(location=raw_unit)
        self._set_uniforms(prog, {**active_parts(prog, atlas.uniforms),
                                  "u_direct_shadow": shadow_unit,
                                  "u_direct_depth": raw_unit,
                                  "u_direct_bias": DIRECT_BIAS_TEXELS,
                                  "u_direct_offset": self._direct_offset})

    def _uniforms(self, camera: Camera, s: RenderSettings) -> dict:
        """Uniform values of the surface shaders (each program takes those it declares)."""
        w, h = s.size
        eye = np.asarray(camera.eye, np.float64)
        centre, radius = self.scene_sphere()
        return {
            "u_view_proj": camera.view_proj(w / h).T.astype("f4").tobytes(),
            "u_eye": tuple(eye),
            "u_albedo": s.albedo,
            "u_key_dir": tuple(key_direction(camera, s)),
            "u_key_irradiance": s.key_irradiance,
            "u_head_irradiance": s.head_irradiance,
            "u_sky_irradiance": s.sky_irradiance,
            "u_ground_irradiance": s.ground_irradiance,
            # where no texel has light yet: the lattice's own sky, else the local modes'
            "u_unbaked_sky": self._unbaked[0] if self._unbaked else s.sky_irradiance,
            "u_unbaked_ground": self._unbaked[1] if self._unbaked else s.ground_irradiance,
            "u_shininess": s.shininess,
            "u_specular": s.specular,
            "u_fog_density": s.fog_density / (2 * radius),
            "u_fog_start": max(float(np.linalg.norm(centre - eye)) - radius, 0.0),
            # the resolve pass shows the background unexposed: fog fades to what shows
            "u_fog_color": tuple(np.asarray(s.background) / s.exposure),
            "u_iso": self._iso if self._iso is not None else 0.0,
        }

    @staticmethod
    def _set_uniforms(prog: moderngl.Program, values: dict) -> None:
        for name, value in values.items():
            if name not in prog:
                continue
            if isinstance(value, bytes):
                prog[name].write(value)
            else:
                prog[name].value = value

    def _bind_shadow_map(self, prog: moderngl.Program, camera: Camera,
                         settings: RenderSettings) -> None:
        """Draw (if needed) and bind the key light's shadow map on texture unit 0."""
        shadow = self._shadows.key_map(settings.shadow_resolution,
                                       key_direction(camera, settings), self.scene_sphere(),
                                       self._mesh_generation)
        shadow.depth.use(location=0)
        texel = 1.0 / shadow.resolution  # depth spans 2 radii over 2 radii of map: 1 texel
        self._set_uniforms(prog, {
            "u_shadow_map": 0,
            "u_light_view_proj": shadow.view_proj.T.astype("f4").tobytes(),
            "u_shadow_bias": (SHADOW_BIAS_TEXELS[0] * texel, SHADOW_BIAS_TEXELS[1] * texel),
        })

    def _prepared_program(self, camera: Camera, settings: RenderSettings) -> moderngl.Program:
        """The surface program of the settings' mode with its uniforms set and its textures
        bound (the shadow map drawn first if the mode needs it); the irradiance lattices
        and the per-pixel lights are bound in `_deferred_pass`."""
        mode = shading_mode(settings.shading)
        prog = self._surface_program(settings)
        self._set_uniforms(prog, self._uniforms(camera, settings))
        if mode.shadow:
            self._bind_shadow_map(prog, camera, settings)
        if settings.shading == "sh" and not self._lattice_deferred(settings):
            self._bind_sh(prog, settings)
        return prog

    def _bind_sh(self, prog: moderngl.Program, settings: RenderSettings) -> None:
        """Bind the SH lattice and its turned environment to `prog`."""
        self.lattice.bind(prog)
        light = self.lattice.light_uniform(self._sh_light(settings))
        prog["u_light"].write(light.tobytes())

    def draw_hdr(self, camera: Camera, settings: RenderSettings,
                 seen: SeenHook | None = None) -> Targets:
        """Draw the mesh in linear radiance into the HDR target (alpha 1 on the surface):
        local and SH modes in the surface pass; the irradiance lattices and the per-pixel
        lights from the G-buffer it leaves (`_deferred_pass`), after `seen` (if given)
        was called with the frame's surface as a position pass gives it, read from that
        G-buffer (`surface_points`): where the per-pixel lights' traced light can be
        made (`set_traced_light`) without a position pass of its own."""
        prog = self._prepared_program(camera, settings) if self._triangles else None
        targets = self._ensure_targets(settings.size)
        targets.hdr.use()
        self.ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        if prog is None:
            return targets
        deferred = self._deferred(settings)
        if deferred:  # with a lattice drawn here, the HDR colour beside the G-buffer
            targets.gbuffer(self.ctx, with_hdr=not self._lattice_deferred(settings)).use()
            self.ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self._draw_mesh(prog)
        if deferred and seen is not None:
            seen(surface_points(targets, camera))
        if deferred:
            self._deferred_pass(targets, camera, settings)
        return targets

    def resolve(self, targets: Targets, settings: RenderSettings,
                fbo: moderngl.Framebuffer | None = None,
                auto: float = 1.0) -> None:
        """Tone-map the HDR target into `fbo` (default: the internal 8-bit target), the
        radiance scaled by the settings' exposure times `auto` (the automatic exposure)."""
        prog = self._program("tonemap", (("TONEMAP", TONEMAPS[settings.tonemap]),))
        (fbo or targets.ldr).use()
        self.ctx.disable(moderngl.DEPTH_TEST)
        targets.hdr_color.use(location=0)
        prog["u_hdr"].value = 0
        prog["u_exposure"].value = settings.exposure * auto
        prog["u_background"].value = settings.background
        vao = self.ctx.vertex_array(prog, [])
        vao.render(moderngl.TRIANGLES, vertices=3)
        vao.release()

    def render(self, camera: Camera, settings: RenderSettings,
               seen: SeenHook | None = None) -> Frame:
        """Draw one frame off-screen and read it back (rows top to bottom); with
        `auto_exposure`, exposed by `auto_exposure_scale` of its surface pixels; `seen`:
        as `draw_hdr`'s."""
        targets = self.draw_hdr(camera, settings, seen)
        w, h = settings.size
        hdr = np.frombuffer(targets.hdr.read(components=4, dtype="f4"), np.float32)
        hdr = hdr.reshape(h, w, 4)[::-1]
        mask = hdr[..., 3] > 0
        auto = auto_exposure_scale(hdr[..., :3], mask) if settings.auto_exposure else 1.0
        if auto != 1.0 and shading_mode(settings.shading).fog:
            # the fog fades to the background divided by the exposure: draw it again
            settings = replace(settings, exposure=settings.exposure * auto,
                               auto_exposure=False)
            targets, auto = self.draw_hdr(camera, settings, seen), 1.0
        self.resolve(targets, settings, auto=auto)
        ldr = np.frombuffer(targets.ldr.read(components=3), np.uint8).reshape(h, w, 3)[::-1]
        return Frame(np.ascontiguousarray(hdr[..., :3]), np.ascontiguousarray(ldr), mask,
                     settings.exposure * auto)


def surface_points(targets: Targets, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points of the surface under a frame's visible pixels and the (H, W)
    mask of those pixels, rows top to bottom — what `app.render.traced_light.position_pass`
    gives — from the eye distances of the G-buffer in `targets` (``gbuffer.glsl``: 0
    where there is no surface) along `camera`'s rays through the pixel centres."""
    w, h = targets.size
    g = np.frombuffer(targets.g_surface.read(), np.float32).reshape(h, w, 4)[::-1, :, 0]
    mask = g > 0
    origins, dirs = camera.primary_rays(w, h, np.flatnonzero(mask))
    return origins + g[mask][:, None].astype(np.float64) * dirs, mask


def default_camera(volume: Volume, view: tuple[float, float, float | None] | None = None) -> Camera:
    """Orbit camera around the centre of `volume`'s sample box (distance in diagonals)."""
    lo, hi = volume.sample_box
    az, el, dist = view if view is not None else (30.0, 30.0, None)
    return Camera(
        azimuth=az, elevation=el, distance=1.8 if dist is None else dist,
        target=tuple((lo + hi) / 2), scale=volume.diagonal,
    )


def framed_camera(volume: Volume, iso: float, view: tuple[float, float, float | None] | None = None,
                  size: tuple[int, int] = (512, 512), *, iso_hi: float | None = None,
                  azimuths: tuple[float, ...] = ()) -> Camera:
    """The camera of ``render``, ``reference`` and ``movie``: at `view`'s azimuth and
    elevation (degrees; None: 30, 30), aimed at the surface at `iso` (the surfaces
    `iso`..`iso_hi`: their points, `volumes.level_points`; the volume's sample box's
    corners when there are none). Without a distance it frames them in a `size` (width,
    height) picture, centred (`app.render.camera.frame_points`); with `azimuths` (a
    turntable's), far enough back to frame them from each, their box centre in the
    middle; with a distance, it stands that many of their box's diagonals from its
    centre."""
    from isolume import volumes

    az, el, dist = view if view is not None else (30.0, 30.0, None)
    points = volumes.level_points(volume, iso, iso_hi)
    if len(points) == 0 or np.ptp(points, axis=0).max() < 1e-6 * volume.diagonal:
        lo, hi = volume.sample_box  # nothing, or a point: show the volume
        points = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                           for z in (lo[2], hi[2])])
    camera = Camera(azimuth=az, elevation=el)
    if dist is not None:
        lo, hi = points.min(axis=0), points.max(axis=0)
        return replace(camera, distance=dist, target=tuple((lo + hi) / 2),
                       scale=float(np.linalg.norm(hi - lo)))
    aspect = size[0] / size[1]
    if not azimuths:
        return frame_points(camera, points, aspect, centre=True)
    framed = [frame_points(replace(camera, azimuth=a), points, aspect) for a in azimuths]
    return replace(framed[0], azimuth=az, distance=max(f.distance for f in framed))
