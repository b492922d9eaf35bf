"""Sampling functions with their densities and inverses; no scene types here.

Densities are per steradian. The random numbers are arguments, so each function can be
tested by a round trip (sample → invert → same u).
"""

from __future__ import annotations

import numpy as np


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (N, 3) unit tangents t, b with (t, b, n) right-handed, for (N, 3) unit normals.

    Duff et al. 2017, "Building an orthonormal basis, revisited" (branchless).
    """
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, bt


def sample_cosine_hemisphere(u: np.ndarray) -> np.ndarray:
    """(N, 3) local directions (z up) with density cos θ / π, from (N, 2) uniforms."""
    r = np.sqrt(u[:, 0])
    phi = 2 * np.pi * u[:, 1]
    z = np.sqrt(np.maximum(0.0, 1 - u[:, 0]))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def cosine_hemisphere_pdf(cos_theta: np.ndarray) -> np.ndarray:
    """Density (1/sr) of `sample_cosine_hemisphere` at directions with these cosines."""
    return np.maximum(cos_theta, 0.0) / np.pi


def invert_cosine_hemisphere(w: np.ndarray) -> np.ndarray:
    """(N, 2) uniforms that `sample_cosine_hemisphere` maps to the (N, 3) local dirs `w`."""
    u0 = w[:, 0] ** 2 + w[:, 1] ** 2
    u1 = np.mod(np.arctan2(w[:, 1], w[:, 0]), 2 * np.pi) / (2 * np.pi)
    return np.stack([u0, u1], axis=1)


def sample_uniform_sphere(u: np.ndarray) -> np.ndarray:
    """(N, 3) unit directions with density 1/(4π), from (N, 2) uniforms."""
    z = 1 - 2 * u[:, 0]
    r = np.sqrt(np.maximum(0.0, 1 - z * z))
    phi = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def to_world(local: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(N, 3) world directions of (N, 3) local (z = normal) directions about normals n."""
    t, b = orthonormal_basis(n)
    return local[:, :1] * t + local[:, 1:2] * b + local[:, 2:3] * n


def power_heuristic(pdf_a: np.ndarray, pdf_b: np.ndarray) -> np.ndarray:
    """MIS weight of strategy a against b (Veach's power heuristic, β = 2)."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    total = a2 + b2
    return np.divide(a2, total, out=np.zeros_like(total), where=total > 0)
