"""Sampling in numpy: the reference the compiled kernels are tested against
(`baking.kernels.cosine_directions` = `sample_cosine_hemisphere` + `to_world`), and the
MIS power heuristic. Random numbers are arguments; no scene types here.
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


def to_world(local: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(N, 3) world directions of (N, 3) local (z = normal) directions about normals n."""
    t, b = orthonormal_basis(n)
    return local[:, :1] * t + local[:, 1:2] * b + local[:, 2:3] * n


def power_heuristic(pdf_a: np.ndarray, pdf_b: np.ndarray) -> np.ndarray:
    """MIS weight of strategy a against b (Veach's power heuristic, β = 2)."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    total = a2 + b2
    return np.divide(a2, total, out=np.zeros_like(total), where=total > 0)
