"""Directions on the sphere: unit-vector checks, luminance, and uniform sphere and cone
sampling (pure functions of the random numbers ``u``)."""

from __future__ import annotations

import math

import numpy as np

FLOOR_FRACTION = 0.02
"""Share of an image sampler's probability spread uniformly (keeps dark pixels reachable)."""

LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
"""Rec. 709 luminance of linear RGB; all positive, so luminance > 0 wherever any channel is."""

FOUR_PI = 4.0 * math.pi




def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance, (..., 3) → (...)."""
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE_WEIGHTS


def as_dirs(dirs: np.ndarray) -> np.ndarray:
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim == 1:
        d = d[None, :]
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {d.shape}")
    return d


def as_u(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 2:
        raise ValueError(f"random numbers must have shape (N, 2), got {u.shape}")
    return u


def readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def fmt(x: float) -> str:
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
