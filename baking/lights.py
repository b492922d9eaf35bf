"""Point and directional lights (hard shadows), parsed from ``--light`` specs.

* ``point:X,Y,Z:R,G,B``: a point light at world (X, Y, Z) with intensity (R, G, B) in
  radiance units × area (W/sr-like); irradiance at distance r, normal incidence: I / r².
* ``dir:X,Y,Z:R,G,B``: a distant light; (X, Y, Z) points *towards* the light, so its
  light travels along −(X, Y, Z); (R, G, B) is the irradiance at normal incidence.

`baking.lighting.Lighting.pixel_lights` lists what a renderer shades per pixel when a
lattice is baked with ``direct_light="pixels"``: these lights and the procedural sky's
sun (`SunLight`, a distant disc whose soft shadow edge comes from its angular radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from isolume.baking.errors import BakeError


@dataclass(frozen=True)
class PointLight:
    position: tuple[float, float, float]
    intensity: tuple[float, float, float]

    @property
    def spec(self) -> str:
        return light_spec("point", self.position, self.intensity)

    def towards(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For (N, 3) points: unit directions to the light, distances, irradiance (N, 3)."""
        d = np.asarray(self.position) - points
        dist = np.linalg.norm(d, axis=1)
        safe = np.maximum(dist, 1e-12)
        e = np.asarray(self.intensity)[None, :] / (safe * safe)[:, None]
        return d / safe[:, None], dist, e


@dataclass(frozen=True)
class DirectionalLight:
    direction: tuple[float, float, float]  # unit, towards the light
    irradiance: tuple[float, float, float]

    @property
    def spec(self) -> str:
        return light_spec("dir", self.direction, self.irradiance)

    def towards(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For (N, 3) points: unit directions to the light, distances (inf), irradiance."""
        n = len(points)
        d = np.broadcast_to(np.asarray(self.direction), (n, 3))
        return d, np.full(n, np.inf), np.broadcast_to(np.asarray(self.irradiance), (n, 3))


@dataclass(frozen=True)
class SunLight:
    """The procedural sky's sun: a disc of uniform radiance (`environment.SkyEnvironment`).

    Attributes:
        direction: (3,) unit vector towards the disc's centre.
        irradiance: (3,) irradiance at normal incidence of the whole disc.
        radius: angular radius, degrees.
    """

    direction: tuple[float, float, float]
    irradiance: tuple[float, float, float]
    radius: float


Light = PointLight | DirectionalLight


def light_spec(kind: str, xyz: npt.ArrayLike, rgb: npt.ArrayLike) -> str:
    """The ``KIND:X,Y,Z:R,G,B`` spec of a light ("point" or "dir"), whose numbers read back
    as the same floats."""
    return f"{kind}:{_join(xyz)}:{_join(rgb)}"


def _join(values) -> str:
    """Numbers as a spec writes them: the shortest text that reads back the same float."""
    return ",".join(_number(v) for v in values)


def _number(value: float) -> str:
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _triple(text: str, spec: str, what: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not np.isfinite(values).all():
        raise BakeError(f"--light {spec!r}: {what} must be three numbers X,Y,Z, got {text!r}")
    return values


def parse_light(spec: str) -> Light:
    """Parse a ``point:X,Y,Z:R,G,B`` or ``dir:X,Y,Z:R,G,B`` spec."""
    parts = spec.split(":")
    if len(parts) != 3 or parts[0] not in ("point", "dir"):
        raise BakeError(
            f"--light {spec!r}: expected point:X,Y,Z:R,G,B or dir:X,Y,Z:R,G,B"
        )
    xyz = _triple(parts[1], spec, "position" if parts[0] == "point" else "direction")
    rgb = _triple(parts[2], spec, "R,G,B")
    if min(rgb) < 0:
        raise BakeError(f"--light {spec!r}: R,G,B must not be negative")
    if parts[0] == "point":
        return PointLight(xyz, rgb)
    norm = float(np.linalg.norm(xyz))
    if norm == 0:
        raise BakeError(f"--light {spec!r}: direction must not be zero")
    return DirectionalLight(tuple(v / norm for v in xyz), rgb)
