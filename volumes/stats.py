"""Summaries of a volume for `isolume info`: histogram and suggested isovalues."""

from __future__ import annotations

import numpy as np
from skimage.filters import threshold_multiotsu

from isolume.volumes.core import Volume

_MAX_SAMPLES = 2_000_000


def _subsample(volume: Volume) -> np.ndarray:
    """A flat, regularly strided subset of at most ~2 M values (deterministic), float32
    (scikit-image bins integer samples otherwise: one bin per value)."""
    flat = volume.data.reshape(-1)
    stride = max(1, flat.size // _MAX_SAMPLES)
    return flat[::stride].astype(np.float32)


def suggest_isovalues(volume: Volume, count: int = 2) -> tuple[float, ...]:
    """Isovalues likely to show structure, most useful first.

    Synthetic volumes know theirs. Otherwise multi-Otsu thresholds with ``count + 1``
    classes (for CT: air | soft tissue | bone → skin and bone surfaces); a constant
    volume has none.
    """
    if volume.suggested_iso:
        return tuple(volume.suggested_iso)
    lo, hi = volume.value_range
    if hi <= lo:
        return ()
    values = _subsample(volume)
    try:
        thresholds = threshold_multiotsu(values, classes=count + 1, nbins=256)
    except ValueError:  # too few distinct values for that many classes
        thresholds = np.array([0.5 * (lo + hi)])
    return tuple(float(t) for t in thresholds if lo < t < hi)


def histogram_lines(volume: Volume, bins: int = 16, width: int = 40) -> list[str]:
    """A text histogram (log-scaled bars) of the values, one line per bin."""
    lo, hi = volume.value_range
    counts, edges = np.histogram(_subsample(volume), bins=bins, range=(lo, max(hi, lo + 1e-12)))
    logc = np.log1p(counts)
    scale = width / logc.max() if logc.max() > 0 else 0
    return [
        f"{edges[i]:>12.5g} .. {edges[i + 1]:<12.5g} {'#' * round(logc[i] * scale)}"
        for i in range(bins)
    ]
