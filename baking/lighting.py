"""`Lighting`: what lights a scene, parsed once from ``--env`` and ``--light`` specs.

A frozen value holding the distant environment model (`baking.environment`: constant,
procedural sky, HDR probe) and the point and directional lights (`baking.lights`). The
baker, the renderer, the viewer and the reference read it; the spec strings exist only
where a user types them and where a lattice file stores them (`to_spec`).

The lights a renderer shades per pixel when a lattice leaves out their direct light
(`pixel_lights`) are the ``--light`` lights and the procedural sky's sun (a `SunLight`,
last). A viewer turns the first distant one of them (`turned`).
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from isolume.baking.environment import Environment, SkyEnvironment, parse_env
from isolume.baking.lights import (
    DirectionalLight,
    Light,
    PointLight,
    SunLight,
    light_spec,
    parse_light,
)

PARSED_KEPT = 64
"""Lightings kept by `lighting_of`, most recently used first: an environment probe is read
and its sampler built once per process, however many configs name it."""
TURN_DIGITS = 9
"""Significant digits of a turned light's direction and of a turned sun's angles (degrees):
the turn of a user's drag, written so that the saved spec reads back the same light."""


@dataclass(frozen=True, eq=False)
class Lighting:
    """A scene's lights.

    Attributes:
        environment: the distant environment, or None (the lights alone).
        lights: point and directional lights, in the order given.
        env_spec: the ``--env`` spec `environment` was parsed from ("" for none).
        light_specs: the ``--light`` specs `lights` were parsed from, one each.
    """

    environment: Environment | None
    lights: tuple[Light, ...] = ()
    env_spec: str = ""
    light_specs: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.light_specs) != len(self.lights):
            raise ValueError(f"{len(self.lights)} lights with {len(self.light_specs)} specs")

    @classmethod
    def parse(cls, env: str, lights: Sequence[str] = ()) -> Lighting:
        """Parse an ``--env`` spec ("" for none) and ``--light`` specs.

        Raises:
            EnvSpecError, BakeError: a bad spec, named with what was expected.
        """
        return cls(parse_env(env) if env else None, tuple(parse_light(s) for s in lights),
                   env, tuple(lights))

    def to_spec(self) -> tuple[str, tuple[str, ...]]:
        """(env spec, light specs): what `parse` reads back as this lighting."""
        return self.env_spec, self.light_specs

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Lighting) and self.to_spec() == other.to_spec()

    def __hash__(self) -> int:
        return hash(self.to_spec())

    @property
    def sky(self) -> SkyEnvironment | None:
        """The procedural sky, when the environment is one."""
        return self.environment if type(self.environment) is SkyEnvironment else None

    @property
    def sun(self) -> SunLight | None:
        """The procedural sky's sun, or None (no sky, or a sky without a sun)."""
        sky = self.sky
        if sky is None or sky.sun_probability == 0:
            return None
        return SunLight(tuple(float(v) for v in sky.sun_direction), tuple(sky.sun),
                        float(sky.sun_radius))

    def pixel_lights(self) -> tuple[PointLight | DirectionalLight | SunLight, ...]:
        """The lights shaded per pixel under ``direct_light="pixels"``: every ``--light``
        and the sky's sun (last)."""
        sun = self.sun
        return self.lights + (() if sun is None else (sun,))

    def turnable(self) -> DirectionalLight | SunLight | None:
        """The light a viewer turns: the first directional light, else the sky's sun."""
        for light in self.pixel_lights():
            if isinstance(light, DirectionalLight | SunLight):
                return light
        return None

    def turned(self, direction: np.ndarray) -> Lighting:
        """This lighting with `turnable` pointing towards `direction` (3,): a directional
        light with the new unit vector, or the sky with the new ``sun_az``/``sun_el``
        (`SkyEnvironment`: (cos el cos az, cos el sin az, sin el)); the rest unchanged.
        The new light is the one its spec (`to_spec`) reads back as.

        Raises:
            ValueError: nothing to turn.
        """
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        for i, light in enumerate(self.lights):
            if isinstance(light, DirectionalLight):
                spec = light_spec("dir", [_rounded(v) for v in d], light.irradiance)
                lights, specs = list(self.lights), list(self.light_specs)
                lights[i], specs[i] = parse_light(spec), spec
                return dataclasses.replace(self, lights=tuple(lights), light_specs=tuple(specs))
        if self.sun is None:
            env, lights = self.to_spec()
            raise ValueError(f"{env!r} {lights}: no per-pixel directional light or sun to "
                             "turn")
        az = _rounded(math.degrees(math.atan2(d[1], d[0])))
        el = _rounded(math.degrees(math.asin(float(np.clip(d[2], -1.0, 1.0)))))
        sky = dataclasses.replace(self.sky, sun_az=az, sun_el=el)
        return dataclasses.replace(self, environment=sky, env_spec=sky.spec)


def _rounded(value: float) -> float:
    """`value` to `TURN_DIGITS` significant digits."""
    return float(f"{value:.{TURN_DIGITS}g}")


_parsed: OrderedDict[tuple[str, tuple[str, ...]], Lighting] = OrderedDict()
_parsed_lock = threading.Lock()


def lighting_of(env: str, lights: Sequence[str] = ()) -> Lighting:
    """`Lighting.parse(env, lights)`, parsed once per process for the same specs (or the
    `Lighting` that `remember` kept under them)."""
    key = (env, tuple(lights))
    with _parsed_lock:
        if key in _parsed:
            _parsed.move_to_end(key)
            return _parsed[key]
    lighting = Lighting.parse(*key)
    return remember(lighting, key)


def remember(lighting: Lighting, key: tuple[str, tuple[str, ...]] | None = None) -> Lighting:
    """Keep `lighting` as what `lighting_of` returns for its specs (`key`, default
    `lighting.to_spec()`); returns it."""
    key = lighting.to_spec() if key is None else key
    with _parsed_lock:
        _parsed[key] = lighting
        _parsed.move_to_end(key)
        while len(_parsed) > PARSED_KEPT:
            _parsed.popitem(last=False)
    return lighting
