"""What a frame looks like: the shading modes, tone curves, `RenderSettings`, and the
`Frame` a render returns.

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
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    from typing import TypeAlias

    from isolume.baking.lights import DirectionalLight, PointLight, SunLight

    DirectLight: TypeAlias = PointLight | DirectionalLight | SunLight
    """A light shaded per pixel (`RenderSettings.direct_lights`)."""


class RenderError(IsolumeError):
    """A frame that cannot be drawn as asked (mode without its lattice or environment)."""


LOOKUPS: dict[str, int] = {"trilinear": 0, "nearest": 1, "closest": 2, "bspline": 3}
"""Irradiance lattice lookups (paper Fig. 6) -> LOOKUP define in ``lattice.glsl``."""


@dataclass(frozen=True)
class ShadingMode:
    """How ``surface.frag`` draws one shading mode.

    Attributes:
        shading: the SHADING define (radiance model, see ``surface.frag``).
        lattice: what the mode reads: None (local model), "irradiance", "sh", or
            "occlusion" (an irradiance lattice baked under a constant sky with no bounces
            and no lights, see `app.render.lights.occlusion_sky`).
        lookup: a key of `LOOKUPS`, how an irradiance lattice is read.
        shadow: the key light is shadow-mapped.
        fog: the radiance fades to the background with eye distance.
    """

    shading: int
    lattice: str | None = None
    lookup: str = "trilinear"
    shadow: bool = False
    fog: bool = False

    @property
    def lattice_kind(self) -> str | None:
        """The kind of lattice the mode reads ("irradiance" or "sh", a `Lattice.kind`;
        None: none): an occlusion lattice is an irradiance one baked under a constant sky
        with no bounces and no lights."""
        if self.lattice is None:
            return None
        return "sh" if self.lattice == "sh" else "irradiance"

    def defines(self) -> tuple[tuple[str, int], ...]:
        """(name, value) shader defines of this mode."""
        return (("SHADING", self.shading), ("SHADOW", int(self.shadow)),
                ("FOG", int(self.fog)), ("LOOKUP", LOOKUPS[self.lookup]))


SHADING_MODES: dict[str, ShadingMode] = {
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
DEBUG_MODES: dict[str, ShadingMode] = {"position": ShadingMode(9)}
"""Modes for tests and picking, not offered to users: world position in the HDR target."""


def shading_mode(name: str) -> ShadingMode:
    """The `ShadingMode` of a key of `SHADING_MODES` or `DEBUG_MODES`."""
    return {**SHADING_MODES, **DEBUG_MODES}[name]


TONEMAPS: dict[str, int] = {"clamp": 0, "reinhard": 1, "aces": 2}
"""Tone curves -> TONEMAP define in ``tonemap.frag``."""

MAX_DIRECT_LIGHTS: int = 8
MAX_DIRECT_TILES: int = 16
"""Per-pixel lights and shadow-atlas tiles ``direct.glsl`` holds (a point light takes 6)."""


def direct_tiles(lights: Iterable[object]) -> list[int]:
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
    direct_lights: tuple[DirectLight, ...] | None = None

    def __post_init__(self) -> None:
        if self.shading not in SHADING_MODES and self.shading not in DEBUG_MODES:
            raise ValueError(
                f"unknown shading mode {self.shading!r}; expected one of "
                f"{', '.join(SHADING_MODES)}"
            )
        if self.tonemap not in TONEMAPS:
            raise ValueError(f"unknown tone map {self.tonemap!r}; expected {', '.join(TONEMAPS)}")
        w, h = self.size
        if not (1 <= w <= 16384 and 1 <= h <= 16384):
            raise ValueError(f"image size {w}x{h} must be between 1 and 16384 per side")
        if not (np.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"exposure must be a positive finite number, got "
                             f"{self.exposure:g}")
        if not 16 <= self.shadow_resolution <= 16384:
            raise ValueError(f"shadow resolution {self.shadow_resolution} must be between 16 "
                             "and 16384 texels")
        if not self.fog_density >= 0:
            raise ValueError(f"fog density must be ≥ 0, got {self.fog_density:g}")
        if self.direct_lights is not None:
            object.__setattr__(self, "direct_lights", tuple(self.direct_lights))
            direct_tiles(self.direct_lights)  # checks kinds and counts


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
