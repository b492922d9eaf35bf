"""Key light and hemisphere ambient for the local shading models of ``isolume chart``,
fitted to the chart's environment so that the local models are lit as fairly as they can
be."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

AMBIENT_ORDER: int = 9
"""SH order of the sky's irradiance for the local models' hemisphere ambient (the clamped
cosine's coefficients fall as l^-2.5: order 9 leaves < 0.2 % of a smooth sky's E)."""


@dataclass(frozen=True)
class LocalLighting:
    """Key light and hemisphere ambient that match an environment (linear RGB irradiance
    at normal incidence).

    Attributes:
        key_dir: (3,) unit vector towards the sun (+z when there is none).
        key: the sun's irradiance (0 without a sun).
        sky, ground: irradiance of the environment without its sun on normals +z and −z.
        mean_radiance: the whole environment's mean radiance (the constant sky of
            "vicinity"/"ao" lattices).
    """

    key_dir: tuple[float, float, float]
    key: tuple[float, float, float]
    sky: tuple[float, float, float]
    ground: tuple[float, float, float]
    mean_radiance: tuple[float, float, float]

    def to_dict(self) -> dict[str, tuple[float, float, float]]:
        return dataclasses.asdict(self)


def local_lighting(env_spec: str) -> LocalLighting:
    """The fairest key light and hemisphere ambient for `env_spec`: a sky's sun becomes the
    key light (its direction and irradiance); the rest of the environment, projected on SH
    and turned into irradiance (Funk–Hecke), gives the ambient for normals ±z."""
    from isolume.baking import sh
    from isolume.baking.environment import SkyEnvironment, parse_env

    env = parse_env(env_spec)
    mean = sh.project_environment(env, 1)[0] / math.sqrt(4 * math.pi)
    key_dir, key, ambient = np.array([0.0, 0.0, 1.0]), np.zeros(3), env
    if isinstance(env, SkyEnvironment) and max(env.sun) > 0:
        key_dir, key = np.asarray(env.sun_direction), np.asarray(env.sun)
        ambient = dataclasses.replace(env, sun=(0.0, 0.0, 0.0))
    up_down = sh.hemisphere_irradiance(ambient, AMBIENT_ORDER)

    def triple(v, floor: float | None = 0.0) -> tuple[float, float, float]:
        return tuple(float(c) for c in (v if floor is None else np.maximum(v, floor)))

    return LocalLighting(triple(key_dir, None), triple(key), triple(up_down[0]),
                         triple(up_down[1]), triple(mean))

