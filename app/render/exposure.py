"""Automatic exposure: the scale that brings a frame's lit surface pixels to middle grey."""

from __future__ import annotations

import numpy as np

EXPOSURE_KEY = 0.18
"""Automatic exposure brings the log-average luminance of the lit surface pixels to this value
(the photographers' middle grey, the "key" of Reinhard et al. 2002 that game engines'
eye adaptation also aims at): under the ACES curve it displays at about 140 of 255."""
BRIGHT_QUANTILE = 0.95
"""The meter's reference of a bright pixel: this quantile of the surface's luminance."""
DARK_FRACTION = 0.02
"""Surface pixels darker than this fraction of the `BRIGHT_QUANTILE` luminance (deep
shadow, unlit patches, black) are left out of the log-average: they carry no exposure
information, and a surface half in such darkness would otherwise be exposed so bright that
its lit half blows out white."""
REC709 = np.array([0.2126, 0.7152, 0.0722])


def auto_exposure_scale(linear: np.ndarray, mask: np.ndarray, key: float = EXPOSURE_KEY,
                        weights: np.ndarray | None = None) -> float:
    """The exposure that brings the log-average luminance of the lit surface pixels to `key`.

    Args:
        linear: (..., 3) linear radiance.
        mask: (...) bool, the surface pixels.
        weights: (...) optional weight of each pixel (e.g. the surface fraction of a block).

    Returns:
        key / exp(mean(log L)) over the surface pixels whose luminance L (Rec. 709
        weights) is at least `DARK_FRACTION` of the `BRIGHT_QUANTILE` luminance of the
        surface's lit (L > 0) pixels; non-finite pixels are left out; 1 when no surface
        pixel is lit.
    """
    lum = np.asarray(np.asarray(linear)[mask], np.float64) @ REC709  # the surface's alone
    if weights is None:
        lum = lum[np.isfinite(lum) & (lum > 0)]
        if not len(lum):
            return 1.0
        lit = lum >= DARK_FRACTION * quantile(lum, BRIGHT_QUANTILE)
        return key / float(np.exp(np.mean(np.log(lum[lit]))))
    w = np.asarray(weights, np.float64)[mask]
    positive = np.isfinite(lum) & (lum > 0) & np.isfinite(w) & (w > 0)
    if not positive.any():
        return 1.0
    lum, w = lum[positive], w[positive]
    lit = lum >= DARK_FRACTION * weighted_quantile(lum, w, BRIGHT_QUANTILE)
    log_average = float(np.exp(np.average(np.log(lum[lit]), weights=w[lit])))
    return key / log_average


def quantile(values: np.ndarray, q: float) -> float:
    """`weighted_quantile` of (N,) `values` all of weight 1 — the value of rank
    ⌈q·N⌉ − 1 — by a partition instead of a sort (a movie's metered frames: millions of
    pixels)."""
    rank = min(max(int(np.ceil(q * len(values))) - 1, 0), len(values) - 1)
    return float(np.partition(values, rank)[rank])


def weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The `q` quantile (0..1) of (N,) `values` with (N,) non-negative `weights`: the
    smallest value whose cumulative weight reaches `q` of the total."""
    order = np.argsort(values, kind="stable")
    cumulative = np.cumsum(weights[order])
    at = int(np.searchsorted(cumulative, q * cumulative[-1]))
    return float(values[order][min(at, len(values) - 1)])
