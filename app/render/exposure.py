"""Automatic exposure: the scale that brings a frame's surface pixels to middle grey."""

from __future__ import annotations

import numpy as np

EXPOSURE_KEY = 0.18
"""Automatic exposure brings the log-average luminance of the surface pixels to this value
(the photographers' middle grey, the "key" of Reinhard et al. 2002 that game engines'
eye adaptation also aims at): under the ACES curve it displays at about 140 of 255."""


def auto_exposure_scale(linear: np.ndarray, mask: np.ndarray, key: float = EXPOSURE_KEY,
                        weights: np.ndarray | None = None) -> float:
    """The exposure that brings the log-average luminance of the surface pixels to `key`.

    Args:
        linear: (..., 3) linear radiance.
        mask: (...) bool, the surface pixels.
        weights: (...) optional weight of each pixel (e.g. the surface fraction of a block).

    Returns:
        key / exp(mean(log L)) over the surface pixels (luminance L, Rec. 709 weights,
        floored at 10⁻³ of the mean so that black pixels do not dominate); 1 when there
        are no surface pixels or they are all black.
    """
    lum = np.asarray(linear, np.float64)[mask] @ np.array([0.2126, 0.7152, 0.0722])
    w = np.ones(len(lum)) if weights is None else np.asarray(weights, np.float64)[mask]
    if len(lum) == 0 or not w.sum() > 0:
        return 1.0
    mean = float(np.average(lum, weights=w))
    if not mean > 0:
        return 1.0
    log_average = float(np.exp(np.average(np.log(np.maximum(lum, 1e-3 * mean)), weights=w)))
    return key / log_average
