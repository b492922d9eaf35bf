"""Distant environment light: constant, procedural sky, HDR image probes; sampling and pdfs.

Conventions
-----------
* World up is +z. A direction ω = (x, y, z) is a unit vector pointing *from* the scene
  *towards* the environment; ``radiance(ω)`` is the radiance arriving from there.
  Spherical angles: ω = (sin θ cos φ, sin θ sin φ, cos θ), θ from +z, φ from +x
  towards +y.
* Radiance is linear RGB, float64 on output. Probability densities are per steradian.
* **Latitude–longitude maps** (W×H, normally W = 2H): row 0 is the top. Pixel
  (row, col) covers θ ∈ π·[row, row+1]/H and φ ∈ 2π·[col, col+1]/W; its centre is
  θ = π(row+0.5)/H, φ = 2π(col+0.5)/W. So the image's centre column looks at −x, the
  left/right edges at +x, and moving right in the image turns from −x towards −y.
  Pixel solid angle (exact): Δφ·(cos θ0 − cos θ1).
* **Angular maps** (Debevec's "light probe" angular map, square N×N): image-plane
  coordinates a = 2(col+0.5)/N − 1 (right +), b = 1 − 2(row+0.5)/N (up +),
  r = sqrt(a² + b²) ≤ 1. The probe's centre looks at **−x** (the same direction as the
  centre of a latlong map), image up is +z and image right is −y (the latlong's layout
  around its centre), so a probe converted between the two layouts by the usual tools
  describes the same environment here. A point at radius r lies at angle ψ = π r from
  −x; the rim r = 1 is the opposite direction +x:
  ω = (−cos πr, −sin(πr)·a/r, sin(πr)·b/r), and r = acos(−x)/π.
  dω = J(r) da db with J(r) = π sin(πr)/r. Pixels that do not meet the unit disk are
  never used; pixel solid angles (the part inside the disk) come from Gauss–Legendre
  quadrature clipped exactly to the disk.
* **OpenEXR's own envmap orientation** (y up) is *not* applied: a latlong EXR is read
  with the layout above, like every other latlong file; turn it with ``rotated``.
* Radiance lookup in an image is the nearest pixel (piecewise constant), so the
  sampling pdf and the radiance agree pixel by pixel.

Sampling (pure functions of the random numbers u ∈ [0,1)²; ``pdf`` is the exact density)
------------------------------------------------------------------------------------
* constant: uniform sphere, pdf 1/4π.
* sky: mixture of a uniform cone over the sun disk (probability p_sun ∝ the sun's share
  of the power, clipped to [0.1, 0.9]) and the uniform sphere.
* image: a pixel with probability p ∝ luminance × solid angle, mixed with 2 %
  (``FLOOR_FRACTION``) of a uniform distribution (by solid angle for latlong, by image
  area over the pixels meeting the disk for angular maps) so that every pixel with
  light is reachable and the estimator stays unbiased. Row then column (pbrt's
  Distribution2D), the remainders of u place the point inside the pixel: uniform in
  (φ, cos θ) for latlong, so pdf = p / Ω_pixel exactly; uniform in image area for
  angular maps, so pdf = Σ_preimages p / (A_pixel · J(r)) (a rim pixel's corner beyond
  r = 1 maps through the same formula onto the directions next to +x, which ``pdf``
  counts as a second preimage).

Specs (``parse_env``)
---------------------
``constant:R,G,B`` | ``constant:V`` | ``sky[:key=value,...]`` |
``PATH[@latlong|@angular][*SCALE]``. Sky keys (colours take 1 or 3 numbers)::

    zenith=0.3,0.5,1.0    radiance straight up
    horizon=1.0           radiance at the horizon (linear in z = cos θ in between)
    ground=0.3            radiance below the horizon
    horizon_blur=3        degrees over which horizon and ground blend (smoothstep in z)
    sun=0                 sun irradiance at normal incidence (0: no sun)
    sun_az=45, sun_el=40  sun direction in degrees (azimuth from +x towards +y, elevation)
    sun_radius=0.5        angular radius of the sun disk in degrees

e.g. ``sky:sun=5,sun_el=30``. Bad specs raise :class:`EnvSpecError`. Negative pixel
values (small filter undershoots are common in real EXRs) are clamped to 0 with a
warning; NaN or infinite pixels are an error.
"""

from __future__ import annotations

import itertools
import math
import re
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from isolume.volumes.errors import IsolumeError

__all__ = [
    "FLOOR_FRACTION",
    "ConstantEnvironment",
    "EnvSpecError",
    "Environment",
    "ImageEnvironment",
    "RotatedEnvironment",
    "SkyEnvironment",
    "angular_dir_to_pixel",
    "angular_pixel_directions",
    "angular_solid_angles",
    "constant",
    "image",
    "image_from_array",
    "latlong_dir_to_pixel",
    "latlong_pixel_directions",
    "latlong_solid_angles",
    "luminance",
    "parse_env",
    "read_exr",
    "read_hdr",
    "read_image",
    "rotated",
    "sample_uniform_cone",
    "sample_uniform_sphere",
    "sky",
    "write_hdr",
]

FLOOR_FRACTION = 0.02
"""Share of an image sampler's probability spread uniformly (keeps dark pixels reachable)."""

LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
"""Rec. 709 luminance of linear RGB; all positive, so luminance > 0 wherever any channel is."""

_FOUR_PI = 4.0 * math.pi


class EnvSpecError(IsolumeError):
    """A bad environment spec or file; the one-line message names it and what was expected."""


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance, (..., 3) → (...)."""
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE_WEIGHTS


def _as_dirs(dirs: np.ndarray) -> np.ndarray:
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim == 1:
        d = d[None, :]
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {d.shape}")
    return d


def _as_u(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 2:
        raise ValueError(f"random numbers must have shape (N, 2), got {u.shape}")
    return u


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _fmt(x: float) -> str:
    return repr(float(x))


# ----------------------------------------------------------------------------- sphere sampling
def sample_uniform_sphere(u: np.ndarray) -> np.ndarray:
    """Uniform directions on the sphere from u (N, 2); density 1/(4π)."""
    z = 1.0 - 2.0 * u[:, 0]
    rho = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = 2.0 * math.pi * u[:, 1]
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


def _orthonormal_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors t, b with (t, b, n) right-handed (Duff et al. 2017), n (3,)."""
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    t = np.array([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    bb = np.array([b, sign + n[1] * n[1] * a, -n[1]])
    return t, bb


def sample_uniform_cone(u: np.ndarray, axis: np.ndarray, cos_max: float) -> np.ndarray:
    """Uniform directions in the cone {ω: ω·axis ≥ cos_max}, density 1/(2π(1 − cos_max))."""
    cos_t = 1.0 - u[:, 0] * (1.0 - cos_max)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    phi = 2.0 * math.pi * u[:, 1]
    t, b = _orthonormal_frame(axis)
    return (
        (sin_t * np.cos(phi))[:, None] * t
        + (sin_t * np.sin(phi))[:, None] * b
        + cos_t[:, None] * axis
    )


# ----------------------------------------------------------------------------- base class
class Environment(ABC):
    """A distant light L(ω): radiance lookup, importance sampling and its exact pdf.

    Subclasses are frozen dataclasses (immutable; their arrays are read-only).
    ``mean_radiance`` (3,) = (1/4π) ∫ L dω; ``spec`` describes it (parseable by
    :func:`parse_env` except for rotated and in-memory environments).
    """

    spec: str
    mean_radiance: np.ndarray

    @abstractmethod
    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        """Radiance arriving from unit directions dirs (N, 3): (N, 3) float64 linear RGB."""

    @abstractmethod
    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Directions (N, 3) and their pdf (N,) per steradian from u (N, 2) in [0, 1)."""

    @abstractmethod
    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        """Exact density (N,) per steradian of ``sample`` at dirs (N, 3)."""

    def rotated(self, r: np.ndarray) -> Environment:
        """This environment turned by the rotation r: L'(ω) = L(rᵀω). See :func:`rotated`."""
        return rotated(self, r)


# ----------------------------------------------------------------------------- constant
@dataclass(frozen=True, eq=False)
class ConstantEnvironment(Environment):
    """Uniform radiance ``rgb`` (3,) from every direction; uniform sphere sampling."""

    rgb: np.ndarray
    spec: str = field(init=False)
    mean_radiance: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        rgb = np.broadcast_to(np.asarray(self.rgb, dtype=np.float64), (3,)).copy()
        if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
            raise ValueError(f"constant radiance must be finite and ≥ 0, got {rgb.tolist()}")
        object.__setattr__(self, "rgb", _readonly(rgb))
        object.__setattr__(self, "mean_radiance", self.rgb)
        object.__setattr__(self, "spec", "constant:" + ",".join(_fmt(v) for v in rgb))

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        d = _as_dirs(dirs)
        return np.broadcast_to(self.rgb, (d.shape[0], 3)).copy()

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = _as_u(u)
        return sample_uniform_sphere(u), np.full(u.shape[0], 1.0 / _FOUR_PI)

    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        return np.full(_as_dirs(dirs).shape[0], 1.0 / _FOUR_PI)


# ----------------------------------------------------------------------------- sky
_SKY_DEFAULTS: dict[str, tuple[float, ...]] = {
    "zenith": (0.3, 0.5, 1.0),
    "horizon": (1.0, 1.0, 1.0),
    "ground": (0.3, 0.3, 0.3),
    "horizon_blur": (3.0,),
    "sun": (0.0, 0.0, 0.0),
    "sun_az": (45.0,),
    "sun_el": (40.0,),
    "sun_radius": (0.5,),
}
_SKY_COLOUR_KEYS = ("zenith", "horizon", "ground", "sun")


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    if edge1 <= edge0:
        return (x >= edge0).astype(np.float64)
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True, eq=False)
class SkyEnvironment(Environment):
    """Procedural sky: a smooth gradient in z plus an optional sun disk (see module docs).

    Gradient: up(z) = horizon + (zenith − horizon)·max(z, 0); with
    g = smoothstep(−h, h, z), h = sin(horizon_blur):
    L_grad(z) = g·up(z) + (1 − g)·ground (a polynomial of degree ≤ 4 between the
    breakpoints −1, −h, 0, h, 1). Sun: constant radiance sun / (π sin² r) inside the
    cone of angular radius r about the sun direction, so that its irradiance at normal
    incidence is exactly ``sun``. Colours (3,); angles in degrees.
    """

    zenith: tuple[float, ...] = _SKY_DEFAULTS["zenith"]
    horizon: tuple[float, ...] = _SKY_DEFAULTS["horizon"]
    ground: tuple[float, ...] = _SKY_DEFAULTS["ground"]
    horizon_blur: float = 3.0
    sun: tuple[float, ...] = (0.0, 0.0, 0.0)
    sun_az: float = 45.0
    sun_el: float = 40.0
    sun_radius: float = 0.5
    spec: str = field(init=False)
    mean_radiance: np.ndarray = field(init=False)
    sun_direction: np.ndarray = field(init=False)
    sun_radiance: np.ndarray = field(init=False)
    sun_cos_radius: float = field(init=False)
    sun_probability: float = field(init=False)

    def __post_init__(self) -> None:
        for key in _SKY_COLOUR_KEYS:
            rgb = tuple(float(v) for v in np.broadcast_to(getattr(self, key), (3,)))
            if not all(math.isfinite(v) and v >= 0 for v in rgb):
                raise ValueError(f"sky {key} must be finite and ≥ 0, got {rgb}")
            object.__setattr__(self, key, rgb)
        if not 0.0 <= self.horizon_blur <= 45.0:
            raise ValueError(f"sky horizon_blur must be in [0, 45] deg, got {self.horizon_blur}")
        if not 0.0 < self.sun_radius <= 45.0:
            raise ValueError(f"sky sun_radius must be in (0, 45] degrees, got {self.sun_radius}")
        if not all(math.isfinite(v) for v in (self.sun_az, self.sun_el)):
            raise ValueError("sky sun_az and sun_el must be finite")
        az, el, rad = (math.radians(v) for v in (self.sun_az, self.sun_el, self.sun_radius))
        s = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        sun_l = np.array(self.sun) / (math.pi * math.sin(rad) ** 2)
        cos_r = math.cos(rad)
        object.__setattr__(self, "sun_direction", _readonly(s))
        object.__setattr__(self, "sun_radiance", _readonly(sun_l))
        object.__setattr__(self, "sun_cos_radius", cos_r)
        sun_power = sun_l * 2.0 * math.pi * (1.0 - cos_r)  # ∫_disk L dω, (3,)
        grad_power = self._gradient_integral()  # ∫ L_grad dω, (3,)
        mean = (sun_power + grad_power) / _FOUR_PI
        object.__setattr__(self, "mean_radiance", _readonly(mean))
        p_sun = 0.0
        if float(luminance(sun_power)) > 0:
            share = float(luminance(sun_power) / luminance(sun_power + grad_power))
            p_sun = min(0.9, max(0.1, share))
        object.__setattr__(self, "sun_probability", p_sun)
        parts = [
            f"{key}=" + ",".join(_fmt(v) for v in np.atleast_1d(getattr(self, key)))
            for key in _SKY_DEFAULTS
        ]
        object.__setattr__(self, "spec", "sky:" + ",".join(parts))

    # -- gradient (zonal part), also used by the SH projection
    def gradient_breakpoints(self) -> np.ndarray:
        """z values between which the gradient is a polynomial (degree ≤ 4): (5,)."""
        h = math.sin(math.radians(self.horizon_blur))
        return np.array([-1.0, -h, 0.0, h, 1.0])

    def gradient_radiance(self, z: np.ndarray) -> np.ndarray:
        """Sky gradient (no sun) at cos θ = z (N,): (N, 3)."""
        z = np.asarray(z, dtype=np.float64)
        h = math.sin(math.radians(self.horizon_blur))
        zen, hor, gnd = (np.asarray(c) for c in (self.zenith, self.horizon, self.ground))
        up = hor + (zen - hor) * np.maximum(z, 0.0)[:, None]
        g = _smoothstep(-h, h, z)[:, None]
        return g * up + (1.0 - g) * gnd

    def _gradient_integral(self) -> np.ndarray:
        nodes, weights = np.polynomial.legendre.leggauss(4)  # exact for degree ≤ 7
        total = np.zeros(3)
        b = self.gradient_breakpoints()
        for z0, z1 in itertools.pairwise(b):
            z = 0.5 * (z1 - z0) * nodes + 0.5 * (z1 + z0)
            total += 0.5 * (z1 - z0) * weights @ self.gradient_radiance(z)
        return 2.0 * math.pi * total

    def without_sun(self) -> SkyEnvironment:
        """The same sky without its sun (what a surface sees of it when the sun's direct
        light is shaded per pixel)."""
        return SkyEnvironment(self.zenith, self.horizon, self.ground, self.horizon_blur,
                              (0.0, 0.0, 0.0), self.sun_az, self.sun_el, self.sun_radius)

    def _in_sun(self, d: np.ndarray) -> np.ndarray:
        return d @ self.sun_direction >= self.sun_cos_radius

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        d = _as_dirs(dirs)
        out = self.gradient_radiance(d[:, 2])
        if self.sun_probability > 0:
            out += self._in_sun(d)[:, None] * self.sun_radiance
        return out

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = _as_u(u)
        p_sun = self.sun_probability
        dirs = np.empty((u.shape[0], 3))
        to_sun = u[:, 0] < p_sun
        if np.any(to_sun):
            us = np.stack([u[to_sun, 0] / p_sun, u[to_sun, 1]], axis=1)
            dirs[to_sun] = sample_uniform_cone(us, self.sun_direction, self.sun_cos_radius)
        rest = ~to_sun
        if np.any(rest):
            us = np.stack([(u[rest, 0] - p_sun) / (1.0 - p_sun), u[rest, 1]], axis=1)
            dirs[rest] = sample_uniform_sphere(np.minimum(us, np.nextafter(1.0, 0.0)))
        return dirs, self.pdf(dirs)

    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        d = _as_dirs(dirs)
        p_sun = self.sun_probability
        out = np.full(d.shape[0], (1.0 - p_sun) / _FOUR_PI)
        if p_sun > 0:
            cone = 2.0 * math.pi * (1.0 - self.sun_cos_radius)
            out += self._in_sun(d) * (p_sun / cone)
        return out


# ----------------------------------------------------------------------------- latlong mapping
def latlong_pixel_directions(h: int, w: int, rows: slice | None = None) -> np.ndarray:
    """Directions of latlong pixel centres: (H, W, 3) (or the given rows)."""
    r = np.arange(h)[rows if rows is not None else slice(None)]
    theta = math.pi * (r + 0.5) / h
    phi = 2.0 * math.pi * (np.arange(w) + 0.5) / w
    st = np.sin(theta)[:, None]
    return np.stack(
        [
            st * np.cos(phi)[None, :],
            st * np.sin(phi)[None, :],
            np.broadcast_to(np.cos(theta)[:, None], (r.size, w)),
        ],
        axis=-1,
    )


def latlong_dir_to_pixel(dirs: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (rows (N,), cols (N,)) containing each direction of dirs (N, 3)."""
    d = _as_dirs(dirs)
    theta = np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2])
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * math.pi)
    rows = np.clip((theta * (h / math.pi)).astype(np.intp), 0, h - 1)
    cols = np.clip((phi * (w / (2.0 * math.pi))).astype(np.intp), 0, w - 1)
    return rows, cols


def latlong_row_solid_angles(h: int, w: int) -> np.ndarray:
    """Exact solid angle of one pixel in each row: Δφ (cos θ0 − cos θ1), (H,)."""
    cos_edges = np.cos(math.pi * np.arange(h + 1) / h)
    return (2.0 * math.pi / w) * (cos_edges[:-1] - cos_edges[1:])


def latlong_solid_angles(h: int, w: int) -> np.ndarray:
    """Exact per-pixel solid angles (H, W) (a read-only broadcast view); total 4π."""
    return np.broadcast_to(latlong_row_solid_angles(h, w)[:, None], (h, w))


# ----------------------------------------------------------------------------- angular mapping
def angular_jacobian(r: np.ndarray) -> np.ndarray:
    """|dω / (da db)| = π |sin πr| / r at image radius r (continued beyond r = 1)."""
    return math.pi * math.pi * np.abs(np.sinc(r))


def angular_image_to_dir(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Directions (N, 3) of image-plane points (a, b); r > 1 continues past +x."""
    r = np.hypot(a, b)
    k = math.pi * np.sinc(r)  # sin(πr)/r
    return np.stack([-np.cos(math.pi * r), -k * a, k * b], axis=-1)


def _angular_polar(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Principal image radius r ∈ [0, 1] and unit in-plane direction (ea, eb) of d (N, 3)."""
    rho = np.hypot(d[:, 1], d[:, 2])
    r = np.arctan2(rho, -d[:, 0]) / math.pi
    safe = np.where(rho > 0, rho, 1.0)
    ea = np.where(rho > 0, -d[:, 1] / safe, 1.0)
    eb = np.where(rho > 0, d[:, 2] / safe, 0.0)
    return r, ea, eb


def angular_dir_to_image(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal image-plane preimage (a (N,), b (N,)) with r ≤ 1 of dirs (N, 3)."""
    r, ea, eb = _angular_polar(_as_dirs(dirs))
    return r * ea, r * eb


def _angular_point_to_pixel(a: np.ndarray, b: np.ndarray, n: int):
    col = np.floor((a + 1.0) * (0.5 * n)).astype(np.intp)
    row = np.floor((1.0 - b) * (0.5 * n)).astype(np.intp)
    inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
    return np.clip(row, 0, n - 1), np.clip(col, 0, n - 1), inside


def angular_dir_to_pixel(dirs: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (rows, cols) of an N×N angular map containing each direction's preimage."""
    a, b = angular_dir_to_image(dirs)
    row, col, _ = _angular_point_to_pixel(a, b, n)
    return row, col


def angular_pixel_directions(n: int, rows: slice | None = None) -> np.ndarray:
    """Directions of angular-map pixel centres (N, N, 3) (or the given rows).

    Centres outside the unit disk (corners of rim pixels) use the continued formula.
    """
    r = np.arange(n)[rows if rows is not None else slice(None)]
    b = 1.0 - 2.0 * (r + 0.5) / n
    a = 2.0 * (np.arange(n) + 0.5) / n - 1.0
    aa, bb = np.meshgrid(a, b)
    return angular_image_to_dir(aa, bb)


def angular_pixels_in_disk(n: int) -> np.ndarray:
    """(N, N) bool: pixels whose square meets the open unit disk."""
    edges = -1.0 + 2.0 * np.arange(n + 1) / n
    lo, hi = edges[:-1], edges[1:]
    near = np.where(lo > 0, lo, np.where(hi < 0, -hi, 0.0))  # distance of [lo, hi] to 0
    # rows run from b = +1 downwards; the set of |b| distances is the same, reversed.
    return near[::-1][:, None] ** 2 + near[None, :] ** 2 < 1.0


def angular_pixels_inside_disk(n: int) -> np.ndarray:
    """(N, N) bool: pixels whose whole square lies in the closed unit disk."""
    edges = np.abs(-1.0 + 2.0 * np.arange(n + 1) / n)
    far = np.maximum(edges[:-1], edges[1:])  # farthest |coordinate| of each pixel span
    return far[::-1][:, None] ** 2 + far[None, :] ** 2 <= 1.0


def _clipped_pixel_integrals(
    rows: np.ndarray, cols: np.ndarray, n: int, nodes: int, split: bool, chunk: int = 1 << 14
) -> np.ndarray:
    """∫ J over (pixel ∩ unit disk) for pixels (rows (P,), cols (P,)) of an N×N map.

    Outer Gauss–Legendre in a (with ``split``: in 5 pieces, split where the circle
    crosses the pixel's top or bottom edge, |a| = sqrt(1 − b_edge²), the kinks of the
    inner integral); inner Gauss–Legendre in b over the b-interval clipped to
    |b| ≤ sqrt(1 − a²). ``nodes`` points per piece.
    """
    xi, wx = np.polynomial.legendre.leggauss(nodes)
    h = 2.0 / n
    out = np.empty(rows.shape[0])
    for p0 in range(0, rows.shape[0], chunk):
        r, c = rows[p0 : p0 + chunk], cols[p0 : p0 + chunk]
        a0 = (-1.0 + c * h)[:, None]
        b_hi = (1.0 - r * h)[:, None]
        b_lo = b_hi - h
        breaks = np.concatenate([a0, a0 + h], axis=1)
        if split:
            kinks = np.sqrt(np.maximum(0.0, 1.0 - np.concatenate([b_lo, b_hi], axis=1) ** 2))
            breaks = np.sort(np.clip(np.concatenate([breaks, kinks, -kinks], 1), a0, a0 + h), 1)
        half = 0.5 * np.diff(breaks, axis=1)  # (P, pieces) half-lengths of the a pieces
        a = (breaks[:, :-1, None] + half[..., None] * (xi + 1.0)).reshape(len(r), -1)
        wa = (half[..., None] * wx).reshape(len(r), -1)
        beta = np.sqrt(np.maximum(0.0, 1.0 - a * a))  # (P, pieces·k)
        lo = np.maximum(b_lo, -beta)
        length = np.maximum(0.0, np.minimum(b_hi, beta) - lo)
        b = lo[..., None] + 0.5 * (xi + 1.0) * length[..., None]  # (P, pieces·k, k)
        inner = 0.5 * length * (angular_jacobian(np.hypot(a[..., None], b)) @ wx)
        out[p0 : p0 + chunk] = np.sum(inner * wa, axis=1)
    return out


def angular_solid_angles(n: int) -> np.ndarray:
    """Solid angle (N, N) of the part of each angular-map pixel inside the unit disk (sr).

    Clipped Gauss–Legendre quadrature of J (``_clipped_pixel_integrals``): 3 nodes per
    axis for pixels wholly inside the disk (J is analytic there), 8 per piece for pixels
    the rim crosses, 0 outside. Where the rim is nearly vertical (|a| > |b|) the
    inner-b clipping meets a square-root edge, so those pixels take the value of their
    mirror image across the diagonal (J is radial), computed where the edge is
    horizontal. Per-pixel relative error 3e-8 at N = 8, 3e-11 at N = 32; total 4π to
    2e-8 at N = 8, 1e-13 at N = 64.
    """
    out = np.zeros((n, n))
    inside = angular_pixels_inside_disk(n)
    rim = angular_pixels_in_disk(n) & ~inside
    for mask, nodes, split in ((inside, 3, False), (rim, 8, True)):
        rows, cols = np.nonzero(mask)
        out[rows, cols] = _clipped_pixel_integrals(rows, cols, n, nodes, split)
    # Pixels (row, col) and (col, row) are mirror images across the line b = −a, so their
    # solid angles are equal (J is radial).
    centres = np.abs(-1.0 + (np.arange(n) + 0.5) * (2.0 / n))
    steep = centres[None, :] > centres[::-1][:, None]  # |a| > |b|
    return np.where(steep, out.T, out)


# ----------------------------------------------------------------------------- pixel sampler
@dataclass(frozen=True, eq=False)
class _PixelSampler:
    """Discrete 2D distribution over pixels: row (marginal), then column (conditional).

    ``p`` (H, W) are the pixel probabilities (sum 1). ``sample(u)`` returns rows, cols
    and the remainders (du for the row, dv for the column), each uniform in [0, 1)
    given the pixel.
    """

    p: np.ndarray
    row_cdf: np.ndarray = field(init=False)
    col_cdf: np.ndarray = field(init=False)
    _flat: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.p, dtype=np.float64)
        p = p / p.sum()
        h, w = p.shape
        p_row = p.sum(axis=1)
        row_cdf = np.concatenate([[0.0], np.cumsum(p_row)])
        row_cdf /= row_cdf[-1]
        cum = np.concatenate([np.zeros((h, 1)), np.cumsum(p, axis=1)], axis=1)
        safe = np.where(p_row > 0, p_row, 1.0)[:, None]
        uniform = np.linspace(0.0, 1.0, w + 1)[None, :]
        col_cdf = np.where(p_row[:, None] > 0, cum / safe, uniform)
        col_cdf[:, -1] = 1.0
        flat = (col_cdf[:, 1:] + 2.0 * np.arange(h)[:, None]).ravel()
        for name, arr in (("p", p), ("row_cdf", row_cdf), ("col_cdf", col_cdf), ("_flat", flat)):
            object.__setattr__(self, name, _readonly(arr))

    def sample(self, u: np.ndarray):
        """u (N, 2) → rows (N,), cols (N,), du (N,), dv (N,)."""
        h, w = self.p.shape
        rows = np.clip(np.searchsorted(self.row_cdf, u[:, 0], side="right") - 1, 0, h - 1)
        lo, hi = self.row_cdf[rows], self.row_cdf[rows + 1]
        du = _remainder(u[:, 0], lo, hi)
        idx = np.searchsorted(self._flat, u[:, 1] + 2.0 * rows, side="right")
        cols = np.clip(idx - rows * w, 0, w - 1)
        lo, hi = self.col_cdf[rows, cols], self.col_cdf[rows, cols + 1]
        dv = _remainder(u[:, 1], lo, hi)
        return rows, cols, du, dv


def _remainder(u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(u − lo) / (hi − lo) clipped to [0, 1): the position of u inside its CDF bin."""
    width = hi - lo
    t = np.divide(u - lo, width, out=np.full_like(u, 0.5), where=width > 0)
    return np.clip(t, 0.0, np.nextafter(1.0, 0.0))


def _mix_with_floor(importance: np.ndarray, floor_measure: np.ndarray) -> np.ndarray:
    """(1 − ε)·importance/Σ + ε·floor_measure/Σ with ε = FLOOR_FRACTION (H, W)."""
    floor = floor_measure / floor_measure.sum()
    total = importance.sum()
    if not total > 0:
        return floor
    return (1.0 - FLOOR_FRACTION) * importance / total + FLOOR_FRACTION * floor


# ----------------------------------------------------------------------------- image environment
_MAPPINGS = ("latlong", "angular")


@dataclass(frozen=True, eq=False)
class ImageEnvironment(Environment):
    """An HDR image probe (nearest-pixel radiance), latlong or angular mapping.

    pixels: (H, W, 3) linear RGB, finite and ≥ 0 (stored float32, read-only, already
    multiplied by ``scale``). ``solid_angles`` (H, W) sr: exact for latlong, clipped
    Gauss–Legendre for angular (0 for pixels outside the disk). ``name`` is the file
    path (or a label for in-memory maps).
    """

    pixels: np.ndarray
    mapping: str
    name: str = "<array>"
    scale: float = 1.0
    spec: str = field(init=False)
    mean_radiance: np.ndarray = field(init=False)
    solid_angles: np.ndarray = field(init=False)
    sampler: _PixelSampler = field(init=False, repr=False)

    def __post_init__(self) -> None:
        px = np.asarray(self.pixels)
        if px.ndim != 3 or px.shape[2] != 3 or min(px.shape[:2]) < 1:
            raise ValueError(f"pixels must have shape (H, W, 3), got {px.shape}")
        if self.mapping not in _MAPPINGS:
            raise ValueError(f"mapping must be 'latlong' or 'angular', got {self.mapping!r}")
        h, w = px.shape[:2]
        if self.mapping == "angular" and h != w:
            raise ValueError(f"an angular map must be square, got {w}x{h}")
        px = np.asarray(px * self.scale, dtype=np.float32)
        if not np.all(np.isfinite(px)) or np.any(px < 0):
            raise ValueError("pixels must be finite and ≥ 0 (after scaling)")
        object.__setattr__(self, "pixels", _readonly(px))
        if self.mapping == "latlong":
            omega = latlong_solid_angles(h, w)
            floor_measure = omega
        else:
            omega = _readonly(angular_solid_angles(h))
            floor_measure = angular_pixels_in_disk(h).astype(np.float64)
        object.__setattr__(self, "solid_angles", omega)
        power = np.einsum("hwc,hw->c", px.astype(np.float64), omega)
        object.__setattr__(self, "mean_radiance", _readonly(power / _FOUR_PI))
        importance = luminance(px) * omega
        sampler = _PixelSampler(_mix_with_floor(importance, floor_measure))
        object.__setattr__(self, "sampler", sampler)
        spec = f"{self.name}@{self.mapping}"
        if self.scale != 1.0:
            spec += f"*{_fmt(self.scale)}"
        object.__setattr__(self, "spec", spec)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image."""
        return self.pixels.shape[:2]

    def pixel_directions(self, rows: slice | None = None) -> np.ndarray:
        """Directions of pixel centres (H, W, 3), or of the given rows."""
        h, w = self.shape
        if self.mapping == "latlong":
            return latlong_pixel_directions(h, w, rows)
        return angular_pixel_directions(h, rows)

    def dir_to_pixel(self, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest-pixel lookup: (rows (N,), cols (N,)) for dirs (N, 3)."""
        h, w = self.shape
        if self.mapping == "latlong":
            return latlong_dir_to_pixel(dirs, h, w)
        return angular_dir_to_pixel(dirs, h)

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        rows, cols = self.dir_to_pixel(dirs)
        return self.pixels[rows, cols].astype(np.float64)

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = _as_u(u)
        rows, cols, du, dv = self.sampler.sample(u)
        h, w = self.shape
        if self.mapping == "latlong":
            cos_edges = np.cos(math.pi * np.arange(h + 1) / h)
            z = cos_edges[rows] - du * (cos_edges[rows] - cos_edges[rows + 1])
            phi = (2.0 * math.pi / w) * (cols + dv)
            rho = np.sqrt(np.maximum(0.0, 1.0 - z * z))
            dirs = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
            pdf = self.sampler.p[rows, cols] / self.solid_angles[rows, cols]
            return dirs, pdf
        a = -1.0 + (cols + dv) * (2.0 / w)
        b = 1.0 - (rows + du) * (2.0 / h)
        dirs = angular_image_to_dir(a, b)
        return dirs, self.pdf(dirs)

    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        d = _as_dirs(dirs)
        h, w = self.shape
        if self.mapping == "latlong":
            rows, cols = latlong_dir_to_pixel(d, h, w)
            return self.sampler.p[rows, cols] / self.solid_angles[rows, cols]
        # Angular: uniform image-area density q = p / A inside a pixel, and two
        # preimages: x1 = r1·e (r1 ≤ 1) and x2 = −(2 − r1)·e (only inside a rim pixel).
        area = (2.0 / h) ** 2
        r1, ea, eb = _angular_polar(d)
        out = np.zeros(d.shape[0])
        for r in (r1, r1 - 2.0):
            row, col, inside = _angular_point_to_pixel(r * ea, r * eb, h)
            jac = np.maximum(angular_jacobian(r), 1e-300)
            out += np.where(inside, self.sampler.p[row, col] / area / jac, 0.0)
        return out


# ----------------------------------------------------------------------------- rotation
@dataclass(frozen=True, eq=False)
class RotatedEnvironment(Environment):
    """``inner`` turned by ``rotation`` (3, 3): L'(ω) = L(Rᵀω); pdf'(ω) = pdf(Rᵀω)."""

    inner: Environment
    rotation: np.ndarray
    spec: str = field(init=False)
    mean_radiance: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        r = np.array(self.rotation, dtype=np.float64)
        if r.shape != (3, 3):
            raise ValueError(f"rotation must be (3, 3), got {r.shape}")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise ValueError("rotation must be orthonormal with determinant +1")
        object.__setattr__(self, "rotation", _readonly(r))
        object.__setattr__(self, "mean_radiance", self.inner.mean_radiance)
        rows = ";".join(",".join(f"{v:.9g}" for v in row) for row in r)
        object.__setattr__(self, "spec", f"{self.inner.spec} rotated by R=[{rows}]")

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        return self.inner.radiance(_as_dirs(dirs) @ self.rotation)  # rows: (Rᵀω)ᵀ = ωᵀR

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dirs, pdf = self.inner.sample(u)
        return dirs @ self.rotation.T, pdf

    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        return self.inner.pdf(_as_dirs(dirs) @ self.rotation)


def rotated(env: Environment, r: np.ndarray) -> Environment:
    """env turned by the proper rotation r (3, 3): L'(ω) = L(rᵀω).

    The SH coefficients of the result are ``baking.sh.rotation(r, n) @ ℓ``. Rotating a
    rotated environment composes the matrices (one level of wrapping).
    """
    if isinstance(env, RotatedEnvironment):
        return RotatedEnvironment(env.inner, np.asarray(r, dtype=np.float64) @ env.rotation)
    return RotatedEnvironment(env, r)


# ----------------------------------------------------------------------------- file reading
def read_exr(path: str | Path) -> tuple[np.ndarray, str | None]:
    """Read an OpenEXR image: (pixels (H, W, 3) float32, envmap kind "latlong"/"cube"/None).

    First part only; channels R, G, B (half or float), or Y (grey); alpha is ignored.
    """
    import OpenEXR  # lazy: only needed for .exr probes

    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = f.header()
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as exc:  # the bindings raise plain RuntimeError/Exception on bad files
        raise EnvSpecError(f"{path}: cannot read as OpenEXR ({exc})") from exc
    envmap = header.get("envmap")
    kind = None
    if envmap is not None:
        kind = "cube" if "CUBE" in str(envmap).upper() else "latlong"
    if all(c in channels for c in "RGB"):
        planes = [channels[c] for c in "RGB"]
    elif "Y" in channels:
        planes = [channels["Y"]] * 3
    else:
        raise EnvSpecError(f"{path}: expected channels R, G, B (or Y), found {sorted(channels)}")
    shapes = {p.shape for p in planes}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise EnvSpecError(f"{path}: channels have different or subsampled shapes {shapes}")
    return np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1), kind


_HDR_RES = re.compile(rb"^([-+])Y\s+(\d+)\s+\+X\s+(\d+)$")


def read_hdr(path: str | Path) -> np.ndarray:
    """Read a Radiance RGBE (.hdr) image: (H, W, 3) float32 linear RGB.

    Supports flat and new-style run-length scanlines, resolution strings ``-Y H +X W``
    (standard, top row first) and ``+Y H +X W`` (bottom row first). Pixel values are
    divided by the product of the header's EXPOSURE values, as the format specifies.
    XYZE files and old-style RLE are refused.
    """
    data = Path(path).read_bytes()
    if not data.startswith(b"#?"):
        raise EnvSpecError(f"{path}: not a Radiance HDR file (no '#?' magic)")
    pos, exposure = 0, 1.0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise EnvSpecError(f"{path}: truncated Radiance header")
        line = data[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT=") and line != b"FORMAT=32-bit_rle_rgbe":
            raise EnvSpecError(
                f"{path}: unsupported {line.decode(errors='replace')}, "
                "expected FORMAT=32-bit_rle_rgbe"
            )
        if line.startswith(b"EXPOSURE="):
            exposure *= float(line[9:])
    end = data.find(b"\n", pos)
    match = _HDR_RES.match(data[pos:end].strip()) if end >= 0 else None
    if match is None:
        raise EnvSpecError(f"{path}: unsupported resolution line, expected '-Y H +X W'")
    h, w = int(match.group(2)), int(match.group(3))
    rgbe = _decode_rgbe(data, end + 1, h, w, path)
    if match.group(1) == b"+":
        rgbe = rgbe[::-1]
    return _rgbe_to_float(rgbe) / np.float32(exposure)


def _decode_rgbe(data: bytes, pos: int, h: int, w: int, path) -> np.ndarray:
    """RGBE bytes (H, W, 4) uint8 from flat or new-style RLE scanlines starting at pos."""
    lines = []
    try:
        for _ in range(h):
            if 8 <= w < 32768 and data[pos] == 2 and data[pos + 1] == 2 and data[pos + 2] < 128:
                if (data[pos + 2] << 8) | data[pos + 3] != w:
                    raise EnvSpecError(f"{path}: RLE scanline width does not match {w}")
                pos += 4
                comps = []
                for _c in range(4):
                    pieces, n = [], 0
                    while n < w:
                        count = data[pos]
                        if count > 128:
                            pieces.append(data[pos + 1 : pos + 2] * (count - 128))
                            pos += 2
                            n += count - 128
                        elif count > 0:
                            pieces.append(data[pos + 1 : pos + 1 + count])
                            pos += 1 + count
                            n += count
                        else:
                            raise EnvSpecError(f"{path}: bad RLE run of length 0")
                    comp = b"".join(pieces)
                    if pos > len(data):
                        raise IndexError("read past the end")
                    if len(comp) != w:
                        raise EnvSpecError(f"{path}: RLE run overruns the scanline")
                    comps.append(np.frombuffer(comp, dtype=np.uint8))
                lines.append(np.stack(comps, axis=1))
            else:
                flat = np.frombuffer(data, dtype=np.uint8, count=4 * w, offset=pos).reshape(w, 4)
                if np.any(np.all(flat[:, :3] == 1, axis=1)):
                    raise EnvSpecError(f"{path}: old-style RLE scanlines are not supported")
                lines.append(flat)
                pos += 4 * w
    except EnvSpecError:
        raise
    except (IndexError, ValueError) as exc:
        raise EnvSpecError(f"{path}: truncated pixel data ({h}x{w} expected)") from exc
    return np.stack(lines, axis=0)


def _rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """(..., 4) uint8 RGBE → (..., 3) float32: (m + 0.5) · 2^(e − 136), 0 where e = 0."""
    e = rgbe[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return ((rgbe[..., :3].astype(np.float64) + 0.5) * f[..., None]).astype(np.float32)


def write_hdr(path: str | Path, rgb: np.ndarray, rle: bool = True) -> None:
    """Write (H, W, 3) finite, non-negative linear RGB as Radiance RGBE (.hdr).

    rle: new-style run-length scanlines (needs 8 ≤ W < 32768), else flat.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_hdr expects (H, W, 3), got {rgb.shape}")
    if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
        raise ValueError("write_hdr needs finite, non-negative values")
    h, w = rgb.shape[:2]
    peak = rgb.max(axis=2)
    mant, expo = np.frexp(peak)
    visible = peak > 1e-38
    scale = np.where(visible, mant * 256.0 / np.where(visible, peak, 1.0), 0.0)
    rgbe = np.zeros((h, w, 4), dtype=np.uint8)
    rgbe[..., :3] = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(visible, expo + 128, 0).astype(np.uint8)
    out = [b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n", f"-Y {h} +X {w}\n".encode()]
    use_rle = rle and 8 <= w < 32768
    for y in range(h):
        if use_rle:
            out.append(bytes([2, 2, w >> 8, w & 255]))
            out.extend(_rle_encode(rgbe[y, :, c].tobytes()) for c in range(4))
        else:
            out.append(rgbe[y].tobytes())
    Path(path).write_bytes(b"".join(out))


def _rle_encode(values: bytes) -> bytes:
    """New-style Radiance RLE of one component: runs of ≥ 4 equal bytes, else literals."""
    out, i, n = bytearray(), 0, len(values)
    while i < n:
        run = 1
        while i + run < n and run < 127 and values[i + run] == values[i]:
            run += 1
        if run >= 4:
            out += bytes([128 + run, values[i]])
            i += run
            continue
        j = i  # literal block until the next run of ≥ 4 (or 128 bytes)
        while j < n and j - i < 128:
            if j + 3 < n and values[j] == values[j + 1] == values[j + 2] == values[j + 3]:
                break
            j += 1
        out += bytes([j - i]) + values[i:j]
        i = j
    return bytes(out)


def read_image(path: str | Path) -> tuple[np.ndarray, str | None]:
    """(pixels (H, W, 3) float32, envmap hint or None) of a .exr or .hdr file."""
    p = Path(path)
    if not p.is_file():
        raise EnvSpecError(f"{path}: no such file (expected an .exr or .hdr probe)")
    ext = p.suffix.lower()
    if ext == ".exr":
        return read_exr(p)
    if ext in (".hdr", ".rgbe", ".pic"):
        return read_hdr(p), None
    raise EnvSpecError(
        f"{path}: unsupported image format {ext or '(none)'!r}, expected .exr or .hdr"
    )


# ----------------------------------------------------------------------------- constructors
def constant(rgb) -> ConstantEnvironment:
    """Uniform environment of radiance rgb (scalar or (3,))."""
    return ConstantEnvironment(np.asarray(rgb, dtype=np.float64))


def sky(**params) -> SkyEnvironment:
    """Procedural sky; keyword parameters as in :class:`SkyEnvironment` / the module docs."""
    return SkyEnvironment(**params)


def _guess_mapping(h: int, w: int, hint: str | None, name: str) -> str:
    if hint == "cube" or (h == 6 * w) or (w == 6 * h) or (3 * w == 4 * h) or (4 * w == 3 * h):
        raise EnvSpecError(
            f"{name}: a {w}x{h} cube map; cube maps are not supported, "
            "expected a latitude-longitude (2:1) or angular (1:1) map"
        )
    if w == 2 * h:
        return "latlong"
    if w == h:
        return "angular"
    raise EnvSpecError(
        f"{name}: {w}x{h} image, expected 2:1 (latlong) or 1:1 (angular); "
        "add @latlong to force a latitude-longitude mapping"
    )


def _validated_pixels(px: np.ndarray, name: str) -> np.ndarray:
    bad = ~np.isfinite(px)
    if np.any(bad):
        row, col, _ = np.argwhere(bad)[0]
        raise EnvSpecError(
            f"{name}: {int(bad.any(axis=2).sum())} pixels are NaN or infinite "
            f"(first at row {row}, col {col}); expected finite radiance"
        )
    if np.any(px < 0):
        count = int((px < 0).any(axis=2).sum())
        warnings.warn(
            f"{name}: {count} pixels had negative values, clamped to 0",
            RuntimeWarning,
            stacklevel=3,
        )
        px = np.maximum(px, 0)
    return px


def image(path: str | Path, mapping: str | None = None, scale: float = 1.0) -> ImageEnvironment:
    """Environment from an .exr / .hdr probe file.

    mapping: "latlong", "angular" or None (2:1 → latlong, 1:1 → angular, cube-map
    layouts and other shapes → EnvSpecError). scale multiplies the radiance.
    """
    name = str(path)
    if mapping is not None and mapping not in _MAPPINGS:
        raise EnvSpecError(f"{name}@{mapping}: unknown mapping, expected @latlong or @angular")
    if not (math.isfinite(scale) and scale >= 0):
        raise EnvSpecError(f"{name}*{scale}: scale must be finite and ≥ 0")
    px, hint = read_image(path)
    h, w = px.shape[:2]
    if mapping is None:
        mapping = _guess_mapping(h, w, hint, name)
    elif mapping == "angular" and h != w:
        raise EnvSpecError(f"{name}@angular: {w}x{h} image, expected a square angular map")
    px = _validated_pixels(px, name)
    return ImageEnvironment(px, mapping, name=name, scale=float(scale))


def image_from_array(pixels: np.ndarray, mapping: str, name: str = "<array>") -> ImageEnvironment:
    """Environment from an in-memory (H, W, 3) map (e.g. synthetic tests)."""
    return ImageEnvironment(np.asarray(pixels), mapping, name=name)


# ----------------------------------------------------------------------------- parse_env
def _parse_numbers(text: str, spec: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise EnvSpecError(f"{spec!r}: expected numbers, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise EnvSpecError(f"{spec!r}: expected finite numbers, got {text!r}")
    return values


def _parse_constant(spec: str, body: str) -> Environment:
    values = _parse_numbers(body, spec)
    if len(values) not in (1, 3) or any(v < 0 for v in values):
        raise EnvSpecError(f"{spec!r}: expected constant:R,G,B or constant:V with values ≥ 0")
    return constant(values if len(values) == 3 else values[0])


def _parse_sky(spec: str, body: str) -> Environment:
    params: dict[str, list[str]] = {}
    key = None
    for token in filter(None, (t.strip() for t in body.split(","))):
        if "=" in token:
            key, value = (s.strip() for s in token.split("=", 1))
            if key not in _SKY_DEFAULTS:
                raise EnvSpecError(
                    f"{spec!r}: unknown sky key {key!r}, expected one of {', '.join(_SKY_DEFAULTS)}"
                )
            params[key] = [value]
        elif key is None:
            raise EnvSpecError(f"{spec!r}: expected sky:key=value,... got {token!r}")
        else:
            params[key].append(token)
    kwargs = {}
    for key, values in params.items():
        numbers = _parse_numbers(",".join(values), spec)
        if key in _SKY_COLOUR_KEYS:
            if len(numbers) not in (1, 3):
                raise EnvSpecError(f"{spec!r}: sky {key} takes 1 or 3 numbers, got {len(numbers)}")
            kwargs[key] = tuple(numbers) if len(numbers) == 3 else (numbers[0],) * 3
        elif len(numbers) != 1:
            raise EnvSpecError(f"{spec!r}: sky {key} takes one number, got {len(numbers)}")
        else:
            kwargs[key] = numbers[0]
    try:
        return SkyEnvironment(**kwargs)
    except ValueError as exc:
        raise EnvSpecError(f"{spec!r}: {exc}") from None


def parse_env(spec: str) -> Environment:
    """Environment from a spec: ``constant:R,G,B``, ``constant:V``, ``sky[:k=v,...]`` or
    ``PATH[@latlong|@angular][*SCALE]``. Raises EnvSpecError (one line, names the spec)."""
    text = spec.strip() if isinstance(spec, str) else ""
    if not text:
        raise EnvSpecError(
            f"{spec!r}: empty environment spec, expected constant:..., "
            "sky[:...] or an .exr/.hdr path"
        )
    head, colon, body = text.partition(":")
    if head == "constant":
        return _parse_constant(spec, body if colon else "1")
    if head == "sky":
        return _parse_sky(spec, body)
    path, mapping, scale = text, None, 1.0
    for _ in range(2):  # suffixes in either order: @mapping, *scale
        m = re.search(r"\*([^*@/\\]+)$", path)
        if m:
            try:
                scale = float(m.group(1))
            except ValueError:
                raise EnvSpecError(f"{spec!r}: expected *SCALE with a number") from None
            path = path[: m.start()]
        m = re.search(r"@([A-Za-z]+)$", path)
        if m:
            mapping, path = m.group(1).lower(), path[: m.start()]
    if mapping is not None and mapping not in _MAPPINGS:
        raise EnvSpecError(f"{spec!r}: unknown mapping @{mapping}, expected @latlong or @angular")
    if not (math.isfinite(scale) and scale >= 0):
        raise EnvSpecError(f"{spec!r}: scale must be finite and ≥ 0")
    if not Path(path).is_file():
        raise EnvSpecError(
            f"{spec!r}: no such file; expected constant:R,G,B, "
            "sky[:key=value,...] or an .exr/.hdr path"
        )
    try:
        return image(path, mapping=mapping, scale=scale)
    except EnvSpecError as exc:
        raise EnvSpecError(f"{spec!r}: {exc}") from None
