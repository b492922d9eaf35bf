"""The lights a frame shades: the key light of the local modes, and the lights a lattice
leaves to the pixels.

A lattice baked with direct light "pixels" holds neither its point and directional lights'
direct light nor its sky's sun's (`lattice_direct_lights`): the renderer adds them per
pixel, shadow-mapped (``direct.glsl``, through `direct_sum`), from the lattice's own start
offset (`lattice_start_offset`). Distant lights turn with the environment in "sh" mode
(`rotated_lights`) or with the viewer's hand (`aimed_lights`). What a lattice says about
its light comes from its bake config (`baking.lattice.Lattice.config`).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from isolume.app.render.camera import Camera
from isolume.app.render.settings import RenderError, RenderSettings, direct_tiles

if TYPE_CHECKING:
    from isolume.app.render.settings import DirectLight
    from isolume.baking.lattice import Lattice
    from isolume.baking.lights import DirectionalLight, SunLight
    from isolume.baking.view_texels import HeldLattice, LatticeOnFile


def key_direction(camera: Camera, settings: RenderSettings) -> np.ndarray:
    """(3,) unit vector towards the key light, world space."""
    if settings.key_dir is not None:
        d = np.asarray(settings.key_dir, np.float64)
        return d / np.linalg.norm(d)
    view = camera.view_matrix()[:3, :3]  # rows: right, up, back
    d = view.T @ np.array([-0.45, 0.6, 0.65])  # from above-left of the eye
    return d / np.linalg.norm(d)


def lattice_direct_lights(lattice: Lattice | HeldLattice | LatticeOnFile | None
                          ) -> tuple[DirectLight, ...]:
    """The lights a lattice leaves to the renderer: its point/directional lights and its
    sky's sun when baked with direct light "pixels" (`baking.lighting.Lighting.pixel_lights`),
    else () (a lattice without the setting holds all its light)."""
    config = lattice.config if lattice is not None else None
    if config is None or config.direct_light != "pixels":
        return ()
    return config.lighting.pixel_lights()


UNBAKED_ORDER = 3
"""SH bands of the environment whose irradiance stands in where no texel has light yet
(`unbaked_hemisphere`): irradiance is a smooth function of the normal, three bands hold
all but a few percent of it."""


def unbaked_hemisphere(lattice: Lattice | HeldLattice | LatticeOnFile | None
                       ) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """((3,), (3,)) RGB irradiance that an open surface facing +z and one facing −z get
    from the lattice's environment — without the sky's sun where the renderer adds it per
    pixel (`lattice_direct_lights`) — by its `UNBAKED_ORDER`-band SH projection: the
    hemisphere ambient the lattice modes show where no texel has light yet, at the light
    level of the texels that have; None where the lattice records no environment. Once a
    process per environment (a movie sets its lattice for every frame)."""
    config = lattice.config if lattice is not None else None
    if config is None or config.lighting.environment is None:
        return None
    return _hemisphere_of(config.env, bool(lattice_direct_lights(lattice)))


@functools.lru_cache(maxsize=8)
def _hemisphere_of(env_spec: str, sun_per_pixel: bool
                   ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """`unbaked_hemisphere` of the environment `env_spec`, without its sun where the sun
    is drawn per pixel."""
    from isolume.baking.lighting import lighting_of
    from isolume.baking.sh import hemisphere_irradiance

    env = lighting_of(env_spec).environment
    if sun_per_pixel and hasattr(env, "without_sun"):
        env = env.without_sun()
    up, down = hemisphere_irradiance(env, UNBAKED_ORDER)
    return tuple(float(v) for v in up), tuple(float(v) for v in down)


def lattice_start_offset(lattice: Lattice | HeldLattice | LatticeOnFile | None) -> float:
    """World distance by which the baker lifted a lattice's start points off the surface
    (its ``offset`` in voxels × the volume's mean spacing): per-pixel direct light is
    looked up from there too, as the reference's shadow rays start there (0 when the
    lattice does not say)."""
    if lattice is None or lattice.config is None:
        return 0.0
    spacing = (lattice.meta.get("volume") or {}).get("spacing")
    if spacing is None:
        return 0.0
    return float(lattice.config.offset) * float(np.mean(spacing))


def occlusion_sky(lattice: Lattice | HeldLattice) -> np.ndarray:
    """(3,) radiance L of the constant sky an occlusion lattice was baked under.

    "vicinity" and "ao" read lattices baked with a constant sky, no bounces and no lights
    (``isolume bake VOLUME --env constant:1,1,1 --bounces 0``): then E/(π·L) is the
    cosine-weighted fraction of the sky a point sees, and albedo·E/π is vicinity shading.

    Raises:
        RenderError: for any other lattice.
    """
    from isolume.baking.environment import ConstantEnvironment

    config = lattice.config
    env, bounces, lights = (("", None, None) if config is None
                            else (config.env, config.bounces, config.lights))
    environment = None if config is None else config.lighting.environment
    constant = isinstance(environment, ConstantEnvironment)
    if lattice.kind != "irradiance" or not constant or bounces != 0 or lights:
        raise RenderError(
            "vicinity shading and ambient occlusion need an irradiance lattice baked under a "
            "constant sky with no bounces and no lights (isolume bake VOLUME --env "
            f"constant:1,1,1 --bounces 0); this one holds {lattice.kind} baked with env "
            f"{env or 'none'!r}, bounces {bounces}, lights {list(lights or [])}")
    sky = np.asarray(environment.rgb, np.float64)
    if not (sky > 0).all():
        raise RenderError(f"the lattice's sky {env!r} is black in some channel: no occlusion "
                          "can be read from it")
    return sky


def rotated_lights(lights: Iterable[DirectLight], env_rotation: tuple[float, float]
                   ) -> tuple[DirectLight, ...]:
    """Distant lights (`DirectionalLight`, `SunLight`) carried along with the environment
    by ``--env-rotation AZ,EL`` (`baking.sh.rotation_from_az_el`: direction d → R·d)."""
    from isolume.baking.sh import rotation_from_az_el

    r = rotation_from_az_el(*env_rotation)
    return tuple(replace(light, direction=tuple(float(v) for v in r @ light.direction))
                 for light in lights)


def aimed_lights(lights: tuple[DirectLight, ...], direction: Sequence[float] | np.ndarray
                 ) -> tuple[DirectLight, ...]:
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


def first_distant_light(lights: Iterable[DirectLight]) -> DirectionalLight | SunLight | None:
    """The first `SunLight` or `DirectionalLight` of `lights`, or None."""
    from isolume.baking.lights import DirectionalLight, SunLight

    return next((light for light in lights
                 if isinstance(light, DirectionalLight | SunLight)), None)


def is_point(light: object) -> bool:
    """Whether `light` is a `baking.lights.PointLight` (six shadow tiles, a position)."""
    from isolume.baking.lights import PointLight

    return isinstance(light, PointLight)


def direct_sum(lights: Sequence[DirectLight]) -> str:
    """The ``DIRECT_SUM(p, n, f)`` body of ``direct.glsl`` for `lights`: one call per light
    with constant light and tile indices (a program per set of light kinds)."""
    from isolume.baking.lights import SunLight

    calls = []
    for i, (light, tile) in enumerate(zip(lights, direct_tiles(lights), strict=True)):
        kind = ("point_light" if is_point(light) else
                "distant_soft" if isinstance(light, SunLight) else "distant_hard")
        calls.append(f"{kind}({i}, {tile}, p, n, f)")
    return "(" + " + ".join(calls) + ")"
