"""Drawing isosurface meshes with moderngl into a linear HDR target, then to display.

`SurfaceRenderer` owns the GL objects for one context: shader programs (one per shading
mode, compiled on first use), the mesh buffers, the framebuffers and the key light's
shadow map. Each frame is drawn in linear radiance into an RGBA32F target (alpha marks
surface pixels), then exposure, tone curve and sRGB encoding are applied in a full-screen
pass. The irradiance lattice modes and the per-pixel lights are shaded deferred: the mesh
pass writes a G-buffer (``gbuffer.glsl``) and one full-screen pass shades each pixel once
(``deferred.frag``), which on llvmpipe costs a fraction of shading the many partly covered
4×4 blocks of a dense mesh's tiny triangles. Everything here works the same in a glfw
window and off-screen.

Shading modes (paper Figs. 1, 6, 8–10), all on the same mesh and camera:

* local: ``lambert`` (key light + headlight), ``phong`` (plus a Blinn–Phong lobe),
  ``lambert_hemi`` / ``phong_hemi`` (plus hemisphere ambient varying with the normal),
  ``lambert_shadow`` / ``phong_shadow`` (the key light shadow-mapped),
  ``lambert_fog`` (fading to the background with eye distance);
* lattice: ``irradiance`` (albedo·E/π, trilinear), its lookup variants of Fig. 6
  ``irradiance_closest`` / ``irradiance_nearest`` / ``irradiance_bspline``, ``sh``
  (transfer under a rotating environment), and from a constant-sky, no-bounce bake
  ``vicinity`` (albedo·E/π) and ``ao`` (E/(π·L_sky) as an occlusion factor on
  hemisphere-ambient Lambert).

The irradiance lattice modes add, per pixel, the direct light of the point and directional
lights and the sky's sun of a lattice baked with direct light "pixels"
(`lattice_direct_lights`, or `RenderSettings.direct_lights`): shadow-mapped from one
linear-depth atlas of tiles, the sun's penumbra from its angular radius (``direct.glsl``).
So does ``sh`` for such a lattice (a split transfer): its sun, turned with the
environment (`rotated_lights`), over the transfer shown under the turned sky without its
sun (direct block) and the whole turned sky (indirect block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import moderngl
import numpy as np

from isolume import shaders
from isolume.app.render.camera import Camera
from isolume.app.render.lattice_gl import MAX_TEXTURE_UNITS, LatticeTextures
from isolume.volumes.errors import IsolumeError

LOOKUPS = {"trilinear": 0, "nearest": 1, "closest": 2, "bspline": 3}
"""Irradiance lattice lookups (paper Fig. 6) -> LOOKUP define in ``lattice.glsl``."""


@dataclass(frozen=True)
class ShadingMode:
    """How ``surface.frag`` draws one shading mode.

    Attributes:
        shading: the SHADING define (radiance model, see ``surface.frag``).
        lattice: what the mode reads: None (local model), "irradiance", "sh", or
            "occlusion" (an irradiance lattice baked under a constant sky with no bounces
            and no lights, see `occlusion_sky`).
        lookup: a key of `LOOKUPS`, how an irradiance lattice is read.
        shadow: the key light is shadow-mapped.
        fog: the radiance fades to the background with eye distance.
    """

    shading: int
    lattice: str | None = None
    lookup: str = "trilinear"
    shadow: bool = False
    fog: bool = False

    def defines(self) -> tuple[tuple[str, int], ...]:
        """(name, value) shader defines of this mode."""
        return (("SHADING", self.shading), ("SHADOW", int(self.shadow)),
                ("FOG", int(self.fog)), ("LOOKUP", LOOKUPS[self.lookup]))


SHADING_MODES = {
    "lambert": ShadingMode(1),  # key light + headlight, albedo·E/π
    "phong": ShadingMode(2),  # lambert + energy-normalised Blinn–Phong lobes
    "lambert_hemi": ShadingMode(3),  # lambert + hemisphere ambient varying with n
    "phong_hemi": ShadingMode(4),  # phong + hemisphere ambient
    "irradiance": ShadingMode(5, "irradiance"),  # albedo·E/π, E trilinear from the lattice
    "sh": ShadingMode(6, "sh"),  # albedo·(Σ τᵢ ℓᵢ)/π under the rotated environment
    "lambert_shadow": ShadingMode(1, shadow=True),  # lambert, key light shadow-mapped
    "phong_shadow": ShadingMode(2, shadow=True),  # phong, key light (and its lobe) shadowed
    "lambert_fog": ShadingMode(1, fog=True),  # lambert fading to the background with depth
    # vicinity shading: the lattice's own radiance, albedo·E/π, of a constant sky L seen
    # past nearby occluders — the GI picture for that sky with no bounces (paper Fig. 10)
    "vicinity": ShadingMode(5, "occlusion"),
    # ambient occlusion: A = E/(π·L) ∈ [0, 1], the sky fraction, is only a factor on
    # another light, here hemisphere ambient: albedo·A·E_hemi(n)/π; no key light, no head
    "ao": ShadingMode(7, "occlusion"),
    # Fig. 6 lookups of E (shown as albedo·E/π): of the 8 texels around the point, the one
    # whose isovalue ρ(x_t) is closest to the mesh's, the nearest one, and (above) their
    # trilinear blend; the uniform cubic B-spline of the 4×4×4 around it
    "irradiance_closest": ShadingMode(5, "irradiance", lookup="closest"),
    "irradiance_nearest": ShadingMode(5, "irradiance", lookup="nearest"),
    "irradiance_bspline": ShadingMode(5, "irradiance", lookup="bspline"),
}
"""Every user-facing shading mode (the long-standing six first: the viewer's keys 1–6)."""
LOCAL_MODES = {name: m for name, m in SHADING_MODES.items() if m.lattice is None}
"""Local shading models (no lattice)."""
LATTICE_MODES = {name: m for name, m in SHADING_MODES.items() if m.lattice is not None}
"""Modes that read an illumination lattice."""
_DEBUG_MODES = {"position": ShadingMode(9)}  # world position in the HDR target (tests, picking)

SHADOW_BIAS_TEXELS = (0.5, 2.5)
"""Shadow-map depth bias, in shadow texels of world depth: constant + slope × tan θ (θ the
angle between facet and key light). The PCF footprint reaches 1 + √2 ≈ 2.41 texels from
the looked-up point (a diagonal tap plus its bilinear neighbours), across which a surface
of slope tan θ changes depth by 2.41 tan θ texels; the constant covers depth rounding and
curvature. Less slope bias shows as acne (tests/test_render_modes.py fails at 2.3)."""
SHADOW_MARGIN = 1.01
"""The light's view spans this many scene-sphere radii (surfaces on the sphere stay in)."""
MAX_DIRECT_LIGHTS = 8
MAX_DIRECT_TILES = 16
"""Per-pixel lights and shadow-atlas tiles ``direct.glsl`` holds (a point light takes 6)."""
DIRECT_BIAS_TEXELS = (0.5, 1.5)
"""Depth bias of the per-pixel lights' shadows, in tile texels: constant + slope × tan θ.
Each filter tap is compared against the receiver's own plane at that tap, so only the
hardware's bilinear 2×2 comparison (≤ 1.5 texels from the tap across a plane of slope
tan θ) and depth rounding need a bias (tests/test_direct_light.py: no acne on lit slopes,
shadows that meet their casters)."""
DIRECT_UNITS = (14, 15)
"""Texture units of the direct lights' shadow atlas: compared, raw (lattices use 1–13)."""
GBUFFER_UNIT = 16
"""Texture unit of the G-buffer the deferred pass reads (a unit of its own, so that no
program's texture is ever the one the surface pass draws into)."""


class RenderError(IsolumeError):
    """A frame that cannot be drawn as asked (mode without its lattice or environment)."""

TONEMAPS = {"clamp": 0, "reinhard": 1, "aces": 2}
EXPOSURE_KEY = 0.18
"""Automatic exposure brings the log-average luminance of the surface pixels to this value
(the photographers' middle grey, the "key" of Reinhard et al. 2002 that game engines'
eye adaptation also aims at): under the ACES curve it displays at about 140 of 255."""


@dataclass(frozen=True)
class RenderSettings:
    """What a frame looks like (not where it is seen from: that is the `Camera`).

    Irradiances are linear RGB at normal incidence; a diffuse surface of albedo a lit by
    E returns radiance a·E/π.

    Attributes:
        size: (width, height) pixels.
        shading: a key of `SHADING_MODES`.
        exposure: linear multiplier applied before the tone curve (on top of the
            automatic exposure when `auto_exposure`).
        auto_exposure: scale the radiance by `auto_exposure_scale` of the frame's surface
            pixels first (`SurfaceRenderer.render`; a window passes its own, smoothed,
            scale to `SurfaceRenderer.resolve`).
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
        shadow_resolution: side of the key light's square shadow map, texels (shadow
            modes).
        direct_lights: the lights shaded per pixel in the irradiance lattice modes
            (`baking.lights.PointLight`, `DirectionalLight`, `SunLight`); None: those of
            the lattice (`lattice_direct_lights`: its point/directional lights and sun
            when it was baked with direct light "pixels", else none).
        fog_density: fog extinction per scene diagonal ("lambert_fog"): a fraction
            T = exp(−fog_density · s / diagonal) of the surface's radiance reaches the eye,
            s the eye distance beyond the near side of the scene's bounding sphere (see
            `SurfaceRenderer.set_bounds`); the rest is fog of radiance background /
            exposure, so distant surfaces fade into the displayed background.
    """

    size: tuple[int, int] = (512, 512)
    shading: str = "phong_hemi"
    exposure: float = 1.0
    auto_exposure: bool = False
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
    shadow_resolution: int = 2048
    fog_density: float = 1.5
    direct_lights: tuple | None = None

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
        if not 16 <= self.shadow_resolution <= 16384:
            raise ValueError(f"shadow resolution {self.shadow_resolution} must be between 16 "
                             "and 16384 texels")
        if not self.fog_density >= 0:
            raise ValueError(f"fog density must be ≥ 0, got {self.fog_density:g}")
        if self.direct_lights is not None:
            object.__setattr__(self, "direct_lights", tuple(self.direct_lights))
            direct_tiles(self.direct_lights)  # checks kinds and counts


def key_direction(camera: Camera, settings: RenderSettings) -> np.ndarray:
    """(3,) unit vector towards the key light, world space."""
    if settings.key_dir is not None:
        d = np.asarray(settings.key_dir, np.float64)
        return d / np.linalg.norm(d)
    view = camera.view_matrix()[:3, :3]  # rows: right, up, back
    d = view.T @ np.array([-0.45, 0.6, 0.65])  # from above-left of the eye
    return d / np.linalg.norm(d)


def light_view_proj(direction: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """(4, 4) world → clip transform of an orthographic view along −`direction` (unit,
    towards the light) that encloses the sphere (`centre` (3,), `radius` world units).

    Clip x, y span the sphere's silhouette; clip z runs from −1 at the sphere's point
    nearest the light to +1 at the farthest, so depth is linear in world distance.
    """
    back = np.asarray(direction, np.float64)
    helper = np.array([0.0, 0.0, 1.0]) if abs(back[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(helper, back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, back
    view[:3, 3] = -view[:3, :3] @ np.asarray(centre, np.float64)
    ortho = np.diag([1.0 / radius, 1.0 / radius, -1.0 / radius, 1.0])
    return ortho @ view


def lattice_direct_lights(lattice) -> tuple:
    """The lights a lattice leaves to the renderer: its point/directional lights and its
    sky's sun when baked with direct light "pixels" (`baking.lights.pixel_lights`), else
    () (a lattice without the setting holds all its light)."""
    config = (lattice.meta.get("config") or {}) if lattice is not None else {}
    if config.get("direct_light") != "pixels":
        return ()
    from isolume.baking.lights import pixel_lights

    return pixel_lights(config.get("env", ""), tuple(config.get("lights", ())))


def lattice_start_offset(lattice) -> float:
    """World distance by which the baker lifted a lattice's start points off the surface
    (its ``offset`` in voxels × the volume's mean spacing): per-pixel direct light is
    looked up from there too, as the reference's shadow rays start there (0 when the
    lattice does not say)."""
    meta = lattice.meta if lattice is not None else {}
    offset = (meta.get("config") or {}).get("offset")
    spacing = (meta.get("volume") or {}).get("spacing")
    if offset is None or spacing is None:
        return 0.0
    return float(offset) * float(np.mean(spacing))


def rotated_lights(lights: tuple, env_rotation: tuple[float, float]) -> tuple:
    """Distant lights (`DirectionalLight`, `SunLight`) carried along with the environment
    by ``--env-rotation AZ,EL`` (`baking.sh.rotation_from_az_el`: direction d → R·d)."""
    from isolume.baking.sh import rotation_from_az_el

    r = rotation_from_az_el(*env_rotation)
    return tuple(replace(light, direction=tuple(float(v) for v in r @ light.direction))
                 for light in lights)


def aimed_lights(lights: tuple, direction) -> tuple:
    """`lights` with the first distant one (the sun or a directional light) turned to point
    towards the unit vector `direction` (3,): a light moved in the viewer. Its direct
    light and shadows follow exactly; the lattice's share of it (its bounces) does not."""
    from isolume.baking.lights import DirectionalLight, SunLight

    out, turned = [], False
    for light in lights:
        if not turned and isinstance(light, DirectionalLight | SunLight):
            d = np.asarray(direction, np.float64)
            light = replace(light, direction=tuple(float(v) for v in d / np.linalg.norm(d)))
            turned = True
        out.append(light)
    return tuple(out)


def first_distant_light(lights: tuple):
    """The first `SunLight` or `DirectionalLight` of `lights`, or None."""
    from isolume.baking.lights import DirectionalLight, SunLight

    return next((light for light in lights
                 if isinstance(light, DirectionalLight | SunLight)), None)


def direct_tiles(lights) -> list[int]:
    """The first shadow-atlas tile of each per-pixel light (a distant light or the sun
    takes one, a point light six).

    Raises:
        RenderError: an unknown kind of light, or more than the shader holds.
    """
    from isolume.baking.lights import DirectionalLight, PointLight, SunLight

    first, tiles = [], 0
    for light in lights:
        if not isinstance(light, DirectionalLight | PointLight | SunLight):
            raise RenderError(f"per-pixel light {light!r}: expected a PointLight, "
                              "DirectionalLight or SunLight")
        first.append(tiles)
        tiles += 6 if isinstance(light, PointLight) else 1
    if len(first) > MAX_DIRECT_LIGHTS or tiles > MAX_DIRECT_TILES:
        raise RenderError(f"{len(first)} per-pixel lights needing {tiles} shadow tiles: at "
                          f"most {MAX_DIRECT_LIGHTS} lights and {MAX_DIRECT_TILES} tiles "
                          "(a point light takes 6); bake the rest with --direct-light lattice")
    return first


_CUBE_FACES = (((1, 0, 0), (0, -1, 0)), ((-1, 0, 0), (0, -1, 0)), ((0, 1, 0), (0, 0, 1)),
               ((0, -1, 0), (0, 0, -1)), ((0, 0, 1), (0, -1, 0)), ((0, 0, -1), (0, -1, 0)))
"""(axis, up) of a point light's six 90° shadow faces, in the order +x −x +y −y +z −z."""


def point_face_view_proj(position: np.ndarray, face: int, near: float, far: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) world → clip transform of face `face` (`_CUBE_FACES`) of a point light at
    `position`, and its linear depth plane (4,): depth = (axis·(p − position)) / far."""
    axis, up = (np.asarray(v, np.float64) for v in _CUBE_FACES[face])
    right = np.cross(axis, up)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -axis
    view[:3, 3] = -view[:3, :3] @ position
    proj = np.zeros((4, 4))  # 90° field of view both ways
    proj[0, 0] = proj[1, 1] = 1.0
    proj[2, 2] = -(far + near) / (far - near)
    proj[2, 3] = -2.0 * far * near / (far - near)
    proj[3, 2] = -1.0
    plane = np.concatenate([axis / far, [-(axis @ position) / far]])
    return proj @ view, plane


def occlusion_sky(lattice) -> np.ndarray:
    """(3,) radiance L of the constant sky an occlusion lattice was baked under.

    "vicinity" and "ao" read lattices baked with a constant sky, no bounces and no lights
    (``isolume bake VOLUME --env constant:1,1,1 --bounces 0``): then E/(π·L) is the
    cosine-weighted fraction of the sky a point sees, and albedo·E/π is vicinity shading.

    Raises:
        RenderError: for any other lattice.
    """
    config = lattice.meta.get("config") or {}
    env, bounces, lights = config.get("env", ""), config.get("bounces"), config.get("lights")
    constant = env.split(":", 1)[0] == "constant"
    if lattice.kind != "irradiance" or not constant or bounces != 0 or lights:
        raise RenderError(
            "vicinity shading and ambient occlusion need an irradiance lattice baked under a "
            "constant sky with no bounces and no lights (isolume bake VOLUME --env "
            f"constant:1,1,1 --bounces 0); this one holds {lattice.kind} baked with env "
            f"{env or 'none'!r}, bounces {bounces}, lights {list(lights or [])}")
    from isolume.baking.environment import parse_env

    sky = np.asarray(parse_env(env).rgb, np.float64)
    if not (sky > 0).all():
        raise RenderError(f"the lattice's sky {env!r} is black in some channel: no occlusion "
                          "can be read from it")
    return sky


@dataclass
class Frame:
    """A rendered image.

    Attributes:
        linear: (H, W, 3) float32 linear radiance (before exposure); 0 off the surface.
        srgb: (H, W, 3) uint8 display image (exposure, tone curve, sRGB).
        mask: (H, W) bool, True on surface pixels.
        exposure: the linear scale applied before the tone curve (the settings' exposure
            times the automatic one).
    """

    linear: np.ndarray
    srgb: np.ndarray
    mask: np.ndarray
    exposure: float = 1.0


def auto_exposure_scale(linear: np.ndarray, mask: np.ndarray, key: float = EXPOSURE_KEY,
                        weights: np.ndarray | None = None) -> float:
    """The exposure that brings the log-average luminance of the surface pixels to `key`.

    Args:
        linear: (..., 3) linear radiance.
        mask: (...) bool, the surface pixels.
        weights: (...) optional weight of each pixel (e.g. the surface fraction of a block).

    Returns:
        key / exp(mean(log L)) over the surface pixels (luminance L, Rec. 709 weights,
        floored at 10⁻³ of the mean so that black pixels do not dominate); 1 when there
        are no surface pixels or they are all black.
    """
    lum = np.asarray(linear, np.float64)[mask] @ np.array([0.2126, 0.7152, 0.0722])
    w = np.ones(len(lum)) if weights is None else np.asarray(weights, np.float64)[mask]
    if len(lum) == 0 or not w.sum() > 0:
        return 1.0
    mean = float(np.average(lum, weights=w))
    if not mean > 0:
        return 1.0
    log_average = float(np.exp(np.average(np.log(np.maximum(lum, 1e-3 * mean)), weights=w)))
    return key / log_average


@dataclass
class _Targets:
    """A frame's render targets: the linear HDR colour with its depth (`hdr`), the 8-bit
    display image (`ldr`) and, once a deferred frame is drawn, the G-buffer of
    ``gbuffer.glsl`` (`g_surface`, RGBA32F) with the framebuffers that draw it: alone
    (`deferred`) or beside the HDR colour (`forward_g`, for SH transfer with lights)."""

    size: tuple[int, int]
    hdr: moderngl.Framebuffer
    hdr_color: moderngl.Texture
    ldr: moderngl.Framebuffer
    depth: moderngl.Renderbuffer
    objects: list = field(default_factory=list)
    g_surface: moderngl.Texture | None = None
    deferred: moderngl.Framebuffer | None = None
    forward_g: moderngl.Framebuffer | None = None

    def gbuffer(self, ctx: moderngl.Context, with_hdr: bool) -> moderngl.Framebuffer:
        """The framebuffer drawing the G-buffer (made on first use), with the HDR colour
        as its first target when `with_hdr`."""
        if self.g_surface is None:
            self.g_surface = ctx.texture(self.size, 4, dtype="f4")
            self.deferred = ctx.framebuffer(color_attachments=[self.g_surface],
                                            depth_attachment=self.depth)
            self.forward_g = ctx.framebuffer(
                color_attachments=[self.hdr_color, self.g_surface], depth_attachment=self.depth)
            self.objects[:0] = [self.deferred, self.forward_g, self.g_surface]
        return self.forward_g if with_hdr else self.deferred

    def release(self) -> None:
        for obj in self.objects:
            obj.release()


@dataclass
class _DirectAtlas:
    """The per-pixel lights' shadow tiles in one depth texture (compared, bilinear), with
    an R32F copy of its depths for the sun's blocker search (`raw`); `key` says what they
    were drawn for, `uniforms` the shader's values for them."""

    depth: moderngl.Texture
    raw: moderngl.Texture
    fbo: moderngl.Framebuffer
    key: tuple | None = None
    uniforms: dict = field(default_factory=dict)

    def release(self) -> None:
        self.fbo.release()
        self.raw.release()
        self.depth.release()


@dataclass
class _ShadowMap:
    """The key light's depth map and what it was drawn for (`key`: mesh generation, light
    direction, scene sphere)."""

    depth: moderngl.Texture
    fbo: moderngl.Framebuffer
    view_proj: np.ndarray | None = None
    key: tuple | None = None

    @property
    def resolution(self) -> int:
        return self.depth.size[0]

    def release(self) -> None:
        self.fbo.release()
        self.depth.release()


class SurfaceRenderer:
    """Renders one isosurface mesh with the shading modes of this module."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self._programs: dict[tuple[str, tuple], moderngl.Program] = {}
        self._mesh_objects: list = []
        self._triangles = 0
        self._mesh_generation = 0
        self._mesh_box: tuple[np.ndarray, np.ndarray] | None = None
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._iso: float | None = None
        self._targets: _Targets | None = None
        self._shadow: _ShadowMap | None = None
        self._atlas: _DirectAtlas | None = None
        self._lattice_lights: tuple = ()
        self._direct_offset = 0.0
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
        `iso` is the isovalue it was extracted at (needed by "irradiance_closest")."""
        for obj in self._mesh_objects:
            obj.release()
        self._mesh_objects, self._triangles = [], len(faces)
        self._mesh_generation += 1
        self._iso = None if iso is None else float(iso)
        if len(faces) == 0:
            self._mesh_box = None
            return
        self._mesh_box = (vertices.min(axis=0).astype(np.float64),
                          vertices.max(axis=0).astype(np.float64))
        interleaved = np.hstack([vertices, normals]).astype(np.float32)
        vbo = self.ctx.buffer(interleaved.tobytes())
        ibo = self.ctx.buffer(np.ascontiguousarray(faces, np.uint32).tobytes())
        self._mesh_objects = [vbo, ibo]
        self._vertex_buffers = (vbo, ibo)

    def set_bounds(self, lo, hi) -> None:
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

    def set_lattice(self, lattice, texel_isovalues: np.ndarray | None = None) -> None:
        """Upload an illumination lattice (`baking.Lattice`) for the lattice modes; None
        removes it. `texel_isovalues` (Z, Y, X): the field value at each texel centre
        (`baking.plan.texel_values(volume, lattice.geometry)`), needed by
        "irradiance_closest"."""
        if self.lattice is not None:
            self.lattice.release()
            self.lattice = None
        self._lattice_lights = lattice_direct_lights(lattice)
        self._direct_offset = lattice_start_offset(lattice)
        if lattice is not None:
            self.lattice = LatticeTextures(self.ctx, lattice, texel_isovalues)

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
        self._targets = _Targets(size, hdr, color, ldr, depth,
                                 [hdr, color, depth, ldr, ldr_color])
        return self._targets

    def _ensure_shadow_map(self, resolution: int) -> _ShadowMap:
        if self._shadow is not None and self._shadow.resolution == resolution:
            return self._shadow
        if self._shadow is not None:
            self._default_fbo.use()
            self._shadow.release()
        depth = self.ctx.depth_texture((resolution, resolution))
        depth.compare_func = "<="  # texture() returns the fraction with reference ≤ stored
        depth.filter = (moderngl.LINEAR, moderngl.LINEAR)  # bilinear 2×2 comparisons
        depth.repeat_x = depth.repeat_y = False
        self._shadow = _ShadowMap(depth, self.ctx.framebuffer(depth_attachment=depth))
        return self._shadow

    def release(self) -> None:
        """Free every GL object this renderer made."""
        for obj in self._mesh_objects:
            obj.release()
        self.set_lattice(None)
        self._default_fbo.use()
        if self._targets is not None:
            self._targets.release()
        if self._shadow is not None:
            self._shadow.release()
        if self._atlas is not None:
            self._atlas.release()
        for prog in self._programs.values():
            prog.release()

    # -- modes -------------------------------------------------------------------------
    def check_mode(self, shading: str) -> None:
        """Raise RenderError unless `shading` can be drawn with what has been set (its
        lattice, environment, texel isovalues and mesh isovalue)."""
        mode = {**SHADING_MODES, **_DEBUG_MODES}[shading]
        if mode.lattice is None:
            return
        if self.lattice is None:
            raise RenderError(f"shading {shading!r} needs a lattice (--lattice FILE)")
        want = "sh" if mode.lattice == "sh" else "irradiance"
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
    def lattice_lights(self) -> tuple:
        """The lights the lattice shown leaves to the pixels (`lattice_direct_lights`)."""
        return self._lattice_lights

    def direct_lights(self, settings: RenderSettings) -> tuple:
        """The lights `settings` shades per pixel: in the irradiance lattice modes the
        settings' own or the lattice's (`RenderSettings.direct_lights`); in "sh" mode the
        sun of a split lattice, turned with the environment (`env_rotation`); else none."""
        mode = {**SHADING_MODES, **_DEBUG_MODES}[settings.shading]
        if mode.lattice == "sh" and self._lattice_lights:
            return rotated_lights(self._lattice_lights, settings.env_rotation)
        if mode.lattice != "irradiance":
            return ()
        if settings.direct_lights is not None:
            return settings.direct_lights
        return self._lattice_lights

    def _lattice_defines(self, settings: RenderSettings) -> tuple:
        """The defines the surface and the deferred program share: the mode's, the SH
        sum's, DEFERRED (`_lattice_deferred`) and DIRECT (per-pixel lights)."""
        defines = {**SHADING_MODES, **_DEBUG_MODES}[settings.shading].defines()
        if settings.shading == "sh":
            defines += self.lattice.sh_defines()
        defines += (("DEFERRED", int(self._lattice_deferred(settings))),)
        if self.direct_lights(settings):
            defines += (("DIRECT", 1),)
        return defines

    def _surface_program(self, settings: RenderSettings) -> moderngl.Program:
        """The compiled surface program for the settings' mode (checks what it needs)."""
        self.check_mode(settings.shading)
        return self._program("surface", self._lattice_defines(settings))

    def _lattice_deferred(self, settings: RenderSettings) -> bool:
        """Whether the settings' lattice is read in `_deferred_pass` (``surface.frag``):
        every lattice mode whose textures fit one pass beside the G-buffer and the shadow
        atlas (GL 3.3's 16 texture units; only SH transfer of high orders does not)."""
        mode = {**SHADING_MODES, **_DEBUG_MODES}[settings.shading]
        if mode.lattice is None:
            return False
        atlas = len(DIRECT_UNITS) if self.direct_lights(settings) else 0
        lattice = self.lattice
        units = 1 + len(lattice.textures) + (lattice.texel_iso is not None)  # + valid mask
        return units + 1 + atlas <= MAX_TEXTURE_UNITS  # + the G-buffer

    def _deferred(self, settings: RenderSettings) -> bool:
        """Whether the settings' frame has a `_deferred_pass`: a deferred lattice, or
        per-pixel lights."""
        return self._lattice_deferred(settings) or bool(self.direct_lights(settings))

    # -- drawing -----------------------------------------------------------------------
    def _draw_shadow_map(self, camera: Camera, settings: RenderSettings) -> _ShadowMap:
        """The key light's depth map for this mesh, light and scene (redrawn on change)."""
        shadow = self._ensure_shadow_map(settings.shadow_resolution)
        centre, radius = self.scene_sphere()
        light = key_direction(camera, settings)
        key = (self._mesh_generation, tuple(light), tuple(centre), radius)
        if shadow.key == key:
            return shadow
        shadow.view_proj = light_view_proj(light, centre, SHADOW_MARGIN * radius)
        prog = self._program("shadow", ())
        prog["u_light_view_proj"].write(shadow.view_proj.T.astype("f4").tobytes())
        shadow.fbo.use()
        self.ctx.clear(depth=1.0)
        self._draw_mesh(prog)
        shadow.key = key
        return shadow

    def _ensure_atlas(self, tile: int, tiles: int) -> _DirectAtlas:
        """A depth atlas holding `tiles` square tiles of `tile` texels (reused when it
        has that size)."""
        cols = math.ceil(math.sqrt(tiles))
        size = (tile * cols, tile * math.ceil(tiles / cols))
        if self._atlas is not None and self._atlas.depth.size == size:
            return self._atlas
        if self._atlas is not None:
            self._default_fbo.use()
            self._atlas.release()
        depth = self.ctx.depth_texture(size)
        depth.compare_func = "<="
        depth.filter = (moderngl.LINEAR, moderngl.LINEAR)
        depth.repeat_x = depth.repeat_y = False
        raw = self.ctx.texture(size, 1, dtype="f4")  # the same depths as floats
        raw.filter = (moderngl.NEAREST, moderngl.NEAREST)
        raw.repeat_x = raw.repeat_y = False
        self._atlas = _DirectAtlas(depth, raw, self.ctx.framebuffer(
            color_attachments=[raw], depth_attachment=depth))
        return self._atlas

    def _draw_direct_atlas(self, lights: tuple, settings: RenderSettings) -> _DirectAtlas:
        """The per-pixel lights' shadow tiles for this mesh and scene (redrawn on change)
        and the shader's uniforms for them."""
        first = direct_tiles(lights)
        tiles = first[-1] + (6 if _is_point(lights[-1]) else 1)
        cols = math.ceil(math.sqrt(tiles))
        tile = min(settings.shadow_resolution, 8192 // cols)
        atlas = self._ensure_atlas(tile, tiles)
        centre, radius = self.scene_sphere()
        key = (self._mesh_generation, lights, tuple(centre), radius, tile)
        if atlas.key == key:
            return atlas
        width, height = atlas.depth.size
        matrices, planes, rects, ranges = [], [], [], []
        for light in lights:
            for view_proj, plane, span in _light_tiles(light, centre, SHADOW_MARGIN * radius):
                i = len(matrices)
                x, y = (i % cols) * tile, (i // cols) * tile
                matrices.append(view_proj)
                planes.append(plane)
                rects.append((x / width, y / height, tile / width, tile / height))
                ranges.append(span)
        prog = self._program("depth", ())
        atlas.fbo.use()
        atlas.fbo.viewport = (0, 0, width, height)
        self.ctx.clear(1.0, 1.0, 1.0, 1.0, depth=1.0)
        for i, (view_proj, plane) in enumerate(zip(matrices, planes, strict=True)):
            atlas.fbo.viewport = (round(rects[i][0] * width), round(rects[i][1] * height),
                                  tile, tile)
            prog["u_view_proj"].write(view_proj.T.astype("f4").tobytes())
            prog["u_depth"].value = tuple(plane)
            self._draw_mesh(prog)
        atlas.fbo.viewport = (0, 0, width, height)
        atlas.uniforms = _direct_uniforms(lights, matrices, planes, rects, ranges,
                                          [tile] * len(matrices))
        atlas.key = key
        return atlas

    def _deferred_pass(self, targets: _Targets, camera: Camera, settings: RenderSettings
                       ) -> None:
        """Add what ``deferred.frag`` shades from the G-buffer the surface pass left: the
        lattice's radiance (`_lattice_deferred`) and the per-pixel lights' direct light
        (the shadow atlas drawn first if the mesh, lights or scene changed); one
        full-screen pass, blending ONE, ONE."""
        mode = {**SHADING_MODES, **_DEBUG_MODES}[settings.shading]
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
        """Draw (if needed) and bind the per-pixel lights' shadow atlas and uniforms."""
        atlas = self._draw_direct_atlas(lights, settings)
        shadow_unit, raw_unit = DIRECT_UNITS
        atlas.depth.use(location=shadow_unit)
        atlas.raw.use(location=raw_unit)
        self._set_uniforms(prog, {**_active_parts(prog, atlas.uniforms),
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
        shadow = self._draw_shadow_map(camera, settings)
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
        mode = {**SHADING_MODES, **_DEBUG_MODES}[settings.shading]
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

    def draw_hdr(self, camera: Camera, settings: RenderSettings) -> _Targets:
        """Draw the mesh in linear radiance into the HDR target (alpha 1 on the surface):
        local and SH modes in the surface pass; the irradiance lattices and the per-pixel
        lights from the G-buffer it leaves (`_deferred_pass`)."""
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
        if deferred:
            self._deferred_pass(targets, camera, settings)
        return targets

    def resolve(self, targets: _Targets, settings: RenderSettings, fbo=None,
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

    def render(self, camera: Camera, settings: RenderSettings) -> Frame:
        """Draw one frame off-screen and read it back (rows top to bottom); with
        `auto_exposure`, exposed by `auto_exposure_scale` of its surface pixels."""
        targets = self.draw_hdr(camera, settings)
        w, h = settings.size
        hdr = np.frombuffer(targets.hdr.read(components=4, dtype="f4"), np.float32)
        hdr = hdr.reshape(h, w, 4)[::-1]
        mask = hdr[..., 3] > 0
        auto = auto_exposure_scale(hdr[..., :3], mask) if settings.auto_exposure else 1.0
        if auto != 1.0 and {**SHADING_MODES, **_DEBUG_MODES}[settings.shading].fog:
            # the fog fades to the background divided by the exposure: draw it again
            settings = replace(settings, exposure=settings.exposure * auto,
                               auto_exposure=False)
            targets, auto = self.draw_hdr(camera, settings), 1.0
        self.resolve(targets, settings, auto=auto)
        ldr = np.frombuffer(targets.ldr.read(components=3), np.uint8).reshape(h, w, 3)[::-1]
        return Frame(np.ascontiguousarray(hdr[..., :3]), np.ascontiguousarray(ldr), mask,
                     settings.exposure * auto)


def pixel_rays(camera: Camera, size: tuple[int, int]) -> dict:
    """``deferred.frag``'s eye rays: the uniforms u_ray0, u_rayx, u_rayy (3,) such that
    the ray through the pixel centre at window coordinates (x, y) (gl_FragCoord: from the
    lower left, centres at half-integers) of a `size` (W, H) view runs along
    u_ray0 + x u_rayx + y u_rayy (not unit: the shader normalises it)."""
    w, h = size
    inverse = np.linalg.inv(camera.view_proj(w / h))
    eye = np.asarray(camera.eye, np.float64)

    def towards(x: float, y: float) -> np.ndarray:  # NDC (x, y) on the far plane
        p = inverse @ np.array([x, y, 1.0, 1.0])
        return p[:3] / p[3] - eye

    # the far plane's points are affine in NDC (a perspective inverse's w depends on z only)
    centre = towards(0.0, 0.0)
    dx, dy = towards(1.0, 0.0) - centre, towards(0.0, 1.0) - centre
    scale = 1.0 / np.linalg.norm(centre)
    return {"u_ray0": tuple(scale * (centre - dx - dy)), "u_rayx": tuple(scale * 2 / w * dx),
            "u_rayy": tuple(scale * 2 / h * dy)}


def _is_point(light) -> bool:
    from isolume.baking.lights import PointLight

    return isinstance(light, PointLight)


def _light_tiles(light, centre: np.ndarray, radius: float):
    """(view_proj (4, 4), linear depth plane (4,), world units per unit of depth) of each
    shadow tile of `light` for a scene within the sphere (`centre`, `radius`)."""
    if _is_point(light):
        position = np.asarray(light.position, np.float64)
        reach = float(np.linalg.norm(position - centre)) + radius
        near = max(1e-4 * reach, reach - 2 * radius)
        for face in range(6):
            view_proj, plane = point_face_view_proj(position, face, near, reach)
            yield view_proj, plane, reach
        return
    direction = np.asarray(light.direction, np.float64)
    view_proj = light_view_proj(direction, centre, radius)
    yield view_proj, 0.5 * view_proj[2] + 0.5 * np.eye(4)[3], 2.0 * radius


def _active_parts(prog: moderngl.Program, arrays: dict) -> dict:
    """The `_direct_uniforms` arrays cut to the lengths the compiled program keeps (a
    compiler drops the tail of an array that only constant indices below it read)."""
    out = {}
    for name, data in arrays.items():
        if name in prog and not isinstance(data, bytes):
            out[name] = data
        elif name in prog:
            declared = MAX_DIRECT_LIGHTS if name.startswith("u_direct") else MAX_DIRECT_TILES
            out[name] = data[:prog[name].array_length * (len(data) // declared)]
    return out


def direct_sum(lights) -> str:
    """The ``DIRECT_SUM(p, n, f)`` body of ``direct.glsl`` for `lights`: one call per light
    with constant light and tile indices (a program per set of light kinds)."""
    from isolume.baking.lights import SunLight

    calls = []
    for i, (light, tile) in enumerate(zip(lights, direct_tiles(lights), strict=True)):
        kind = ("point_light" if _is_point(light) else
                "distant_soft" if isinstance(light, SunLight) else "distant_hard")
        calls.append(f"{kind}({i}, {tile}, p, n, f)")
    return "(" + " + ".join(calls) + ")"


def _direct_uniforms(lights, matrices, planes, rects, ranges, tile_texels) -> dict:
    """The ``direct.glsl`` uniform arrays (padded to their declared sizes); `tile_texels`:
    each tile's side in texels."""
    from isolume.baking.lights import SunLight

    def padded(rows, width, count, dtype="f4"):
        out = np.zeros((count, width), dtype)
        out[:len(rows)] = rows
        return out.tobytes()

    where = [(*light.position, 1.0) if _is_point(light) else (*light.direction, 0.0)
             for light in lights]
    rgb = [light.intensity if _is_point(light) else light.irradiance for light in lights]
    tan_r = [[math.tan(math.radians(light.radius))] if isinstance(light, SunLight) else [0.0]
             for light in lights]
    axes = [m[:2, :3] / np.linalg.norm(m[:2, :3], axis=1, keepdims=True) for m in matrices]
    n, t = MAX_DIRECT_LIGHTS, MAX_DIRECT_TILES
    return {
        "u_direct_where": padded(where, 4, n), "u_direct_rgb": padded(rgb, 3, n),
        "u_direct_tan_radius": padded(tan_r, 1, n),
        "u_tile_view_proj": b"".join(m.T.astype("f4").tobytes() for m in matrices)
        + bytes(64 * (t - len(matrices))),
        "u_tile_depth": padded(planes, 4, t), "u_tile_rect": padded(rects, 4, t),
        "u_tile_range": padded([[r] for r in ranges], 1, t),
        "u_tile_right": padded([a[0] for a in axes], 3, t),
        "u_tile_up": padded([a[1] for a in axes], 3, t),
        "u_tile_texel": padded([[1.0 / texels] for texels in tile_texels], 1, t),
    }


def default_camera(volume, view: tuple[float, float, float | None] | None = None) -> Camera:
    """Orbit camera around the centre of `volume`'s sample box (distance in diagonals)."""
    lo, hi = volume.sample_box
    az, el, dist = view if view is not None else (30.0, 30.0, None)
    return Camera(
        azimuth=az, elevation=el, distance=1.8 if dist is None else dist,
        target=tuple((lo + hi) / 2), scale=volume.diagonal,
    )
