"""Images of ``isolume chart`` and their error against the path-traced reference.

Error: relative RMSE of linear radiance, ``sqrt(mean((img − ref)²)) / mean(ref)`` over the
pixels that both images mark as surface and over their RGB values (`relative_rmse`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from isolume.baking.reference import ReferenceImage


@dataclass
class Image:
    """A rendered picture, flat in pixels (row-major from the top-left).

    Attributes:
        linear: (N, 3) float64 linear radiance.
        mask: (N,) bool, True on surface pixels.
    """

    linear: np.ndarray
    mask: np.ndarray


def relative_rmse(image: Image, reference: ReferenceImage) -> tuple[float | None, int]:
    """(error, pixels): ``sqrt(mean((img − ref)²)) / mean(ref)`` over the RGB values of the
    pixels both mark as surface (`reference`: a `baking.reference.ReferenceImage`); None
    when they share no pixel."""
    both = image.mask & reference.mask
    if not both.any():
        return None, 0
    ref = reference.radiance[both]
    diff = image.linear[both] - ref
    return float(np.sqrt(np.mean(diff * diff)) / np.mean(ref)), int(both.sum())


def error_record(image: Image, reference: ReferenceImage) -> dict[str, Any]:
    """"error" and "pixels" (`relative_rmse`) plus "error_less_reference_noise":
    ``sqrt(max(error² − noise², 0))`` with the reference's noise over the same pixels,
    an estimate of the error against the exact image (E(img − ref)² = (img − exact)² +
    stderr² pixel by pixel). Informative only: the charts plot "error"."""
    error, pixels = relative_rmse(image, reference)
    if error is None:
        return {"error": None, "pixels": 0, "error_less_reference_noise": None}
    both = image.mask & reference.mask
    noise = np.sqrt(np.mean(reference.stderr[both] ** 2)) / np.mean(reference.radiance[both])
    return {"error": error, "pixels": pixels,
            "error_less_reference_noise": float(np.sqrt(max(error**2 - noise**2, 0.0)))}


def reference_noise(reference: ReferenceImage) -> float:
    """``sqrt(mean(stderr²)) / mean(ref)`` over the RGB values of the reference's surface
    pixels: the relative error its own Monte Carlo noise contributes (inf with < 2 spp)."""
    m = reference.mask
    if not m.any():
        return 0.0
    return float(np.sqrt(np.mean(reference.stderr[m] ** 2)) / np.mean(reference.radiance[m]))


def image_entries(node: object) -> list[dict[str, Any]]:
    """Every dict under `node` (nested dicts and lists) that names an image."""
    if isinstance(node, dict):
        found = [node] if "image" in node else []
        return found + [e for v in node.values() for e in image_entries(v)]
    if isinstance(node, list):
        return [e for v in node for e in image_entries(v)]
    return []

