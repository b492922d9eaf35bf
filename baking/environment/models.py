"""Environment models: constant, procedural sky, HDR image probe and rotated
environments — radiance, importance sampling and the exact pdf (conventions in
`baking.environment`)."""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from isolume.baking.environment.maps import (
    angular_dir_to_pixel,
    angular_image_to_dir,
    angular_jacobian,
    angular_pixel_directions,
    angular_pixels_in_disk,
    angular_point_to_pixel,
    angular_polar,
    angular_solid_angles,
    latlong_dir_to_pixel,
    latlong_pixel_directions,
    latlong_solid_angles,
)
from isolume.baking.environment.sphere import (
    FLOOR_FRACTION,
    FOUR_PI,
    as_dirs,
    as_u,
    fmt,
    luminance,
    readonly,
    sample_uniform_cone,
    sample_uniform_sphere,
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
        object.__setattr__(self, "rgb", readonly(rgb))
        object.__setattr__(self, "mean_radiance", self.rgb)
        object.__setattr__(self, "spec", "constant:" + ",".join(fmt(v) for v in rgb))

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        d = as_dirs(dirs)
        return np.broadcast_to(self.rgb, (d.shape[0], 3)).copy()

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = as_u(u)
        return sample_uniform_sphere(u), np.full(u.shape[0], 1.0 / FOUR_PI)

    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        return np.full(as_dirs(dirs).shape[0], 1.0 / FOUR_PI)


# ----------------------------------------------------------------------------- sky
SKY_DEFAULTS: dict[str, tuple[float, ...]] = {
    "zenith": (0.3, 0.5, 1.0),
    "horizon": (1.0, 1.0, 1.0),
    "ground": (0.3, 0.3, 0.3),
    "horizon_blur": (3.0,),
    "sun": (0.0, 0.0, 0.0),
    "sun_az": (45.0,),
    "sun_el": (40.0,),
    "sun_radius": (0.5,),
}
SKY_COLOUR_KEYS = ("zenith", "horizon", "ground", "sun")


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

    zenith: tuple[float, ...] = SKY_DEFAULTS["zenith"]
    horizon: tuple[float, ...] = SKY_DEFAULTS["horizon"]
    ground: tuple[float, ...] = SKY_DEFAULTS["ground"]
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
        for key in SKY_COLOUR_KEYS:
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
        object.__setattr__(self, "sun_direction", readonly(s))
        object.__setattr__(self, "sun_radiance", readonly(sun_l))
        object.__setattr__(self, "sun_cos_radius", cos_r)
        sun_power = sun_l * 2.0 * math.pi * (1.0 - cos_r)  # ∫_disk L dω, (3,)
        grad_power = self._gradient_integral()  # ∫ L_grad dω, (3,)
        mean = (sun_power + grad_power) / FOUR_PI
        object.__setattr__(self, "mean_radiance", readonly(mean))
        p_sun = 0.0
        if float(luminance(sun_power)) > 0:
            share = float(luminance(sun_power) / luminance(sun_power + grad_power))
            p_sun = min(0.9, max(0.1, share))
        object.__setattr__(self, "sun_probability", p_sun)
        parts = [
            f"{key}=" + ",".join(fmt(v) for v in np.atleast_1d(getattr(self, key)))
            for key in SKY_DEFAULTS
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
        d = as_dirs(dirs)
        out = self.gradient_radiance(d[:, 2])
        if self.sun_probability > 0:
            out += self._in_sun(d)[:, None] * self.sun_radiance
        return out

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = as_u(u)
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
        d = as_dirs(dirs)
        p_sun = self.sun_probability
        out = np.full(d.shape[0], (1.0 - p_sun) / FOUR_PI)
        if p_sun > 0:
            cone = 2.0 * math.pi * (1.0 - self.sun_cos_radius)
            out += self._in_sun(d) * (p_sun / cone)
        return out




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
            object.__setattr__(self, name, readonly(arr))

    def sample(self, u: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
MAPPINGS = ("latlong", "angular")


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
        if self.mapping not in MAPPINGS:
            raise ValueError(f"mapping must be 'latlong' or 'angular', got {self.mapping!r}")
        h, w = px.shape[:2]
        if self.mapping == "angular" and h != w:
            raise ValueError(f"an angular map must be square, got {w}x{h}")
        px = np.asarray(px * self.scale, dtype=np.float32)
        if not np.all(np.isfinite(px)) or np.any(px < 0):
            raise ValueError("pixels must be finite and ≥ 0 (after scaling)")
        object.__setattr__(self, "pixels", readonly(px))
        if self.mapping == "latlong":
            omega = latlong_solid_angles(h, w)
            floor_measure = omega
        else:
            omega = readonly(angular_solid_angles(h))
            floor_measure = angular_pixels_in_disk(h).astype(np.float64)
        object.__setattr__(self, "solid_angles", omega)
        power = np.einsum("hwc,hw->c", px.astype(np.float64), omega)
        object.__setattr__(self, "mean_radiance", readonly(power / FOUR_PI))
        importance = luminance(px) * omega
        sampler = _PixelSampler(_mix_with_floor(importance, floor_measure))
        object.__setattr__(self, "sampler", sampler)
        spec = f"{self.name}@{self.mapping}"
        if self.scale != 1.0:
            spec += f"*{fmt(self.scale)}"
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
        u = as_u(u)
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
        d = as_dirs(dirs)
        h, w = self.shape
        if self.mapping == "latlong":
            rows, cols = latlong_dir_to_pixel(d, h, w)
            return self.sampler.p[rows, cols] / self.solid_angles[rows, cols]
        # Angular: uniform image-area density q = p / A inside a pixel, and two
        # preimages: x1 = r1·e (r1 ≤ 1) and x2 = −(2 − r1)·e (only inside a rim pixel).
        area = (2.0 / h) ** 2
        r1, ea, eb = angular_polar(d)
        out = np.zeros(d.shape[0])
        for r in (r1, r1 - 2.0):
            row, col, inside = angular_point_to_pixel(r * ea, r * eb, h)
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
        object.__setattr__(self, "rotation", readonly(r))
        object.__setattr__(self, "mean_radiance", self.inner.mean_radiance)
        rows = ";".join(",".join(f"{v:.9g}" for v in row) for row in r)
        object.__setattr__(self, "spec", f"{self.inner.spec} rotated by R=[{rows}]")

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        return self.inner.radiance(as_dirs(dirs) @ self.rotation)  # rows: (Rᵀω)ᵀ = ωᵀR

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dirs, pdf = self.inner.sample(u)
        return dirs @ self.rotation.T, pdf

    def pdf(self, dirs: np.ndarray) -> np.ndarray:
        return self.inner.pdf(as_dirs(dirs) @ self.rotation)


def rotated(env: Environment, r: np.ndarray) -> Environment:
    """env turned by the proper rotation r (3, 3): L'(ω) = L(rᵀω).

    The SH coefficients of the result are ``baking.sh.rotation(r, n) @ ℓ``. Rotating a
    rotated environment composes the matrices (one level of wrapping).
    """
    if isinstance(env, RotatedEnvironment):
        return RotatedEnvironment(env.inner, np.asarray(r, dtype=np.float64) @ env.rotation)
    return RotatedEnvironment(env, r)
