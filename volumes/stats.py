"""Summaries of a volume for `isolume info`: histogram and suggested isovalues."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    try:
        thresholds = multi_otsu(_subsample(volume), count + 1)
    except ValueError:  # too few distinct values for that many classes
        thresholds = np.array([0.5 * (lo + hi)])
    return tuple(float(t) for t in thresholds if lo < t < hi)


def multi_otsu(values: np.ndarray, classes: int, bins: int = 256) -> np.ndarray:
    """(classes - 1,) field units: the multi-Otsu thresholds of the (N,) float32 `values`
    over `bins` bins, the same bits as ``skimage.filters.threshold_multiotsu`` (its
    histogram and its compiled search, called without that module, whose import of SciPy's
    ndimage adds 0.08 s to the serial start of every command that suggests an isovalue).

    Raises:
        ValueError: fewer than `classes` bins hold values.
    """
    from skimage.exposure import histogram as binned
    from skimage.filters._multiotsu import _get_multiotsu_thresh_indices_lut

    prob, centers = binned(values, bins, source_range="image", normalize=True)
    prob = prob.astype(np.float32, copy=False)
    held = np.count_nonzero(prob)
    if held < classes:
        raise ValueError(f"{held} bins hold values, {classes} classes asked for")
    if held == classes:
        return centers[np.flatnonzero(prob)[:-1]]
    return centers[_get_multiotsu_thresh_indices_lut(prob, classes - 1)]


def histogram(volume: Volume, bins: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(bins,) counts and (bins + 1,) float64 edges (field units) of the values over
    their range, from at most `_MAX_SAMPLES` of them (evenly strided).

    The edges are computed in float64: float32 ones coincide where the range is narrow
    beside the values' magnitude (1e8 + [0, 100]). A constant volume's one value is the
    middle of a single-width range (`_value_span`)."""
    lo, hi = _value_span(*volume.value_range)
    return np.histogram(_subsample(volume).astype(np.float64), bins=bins, range=(lo, hi))


def _value_span(lo: float, hi: float) -> tuple[float, float]:
    """(lo, hi) as histogram limits, float64: as they are where ``hi > lo``; around a
    constant value, ±0.5, or ±2⁻²⁰ of its magnitude where that is wider (±0.5 is lost in
    the rounding of values beyond 2⁵²)."""
    if hi > lo:
        return float(lo), float(hi)
    half = max(0.5, abs(lo) * 2.0**-20)
    return float(lo) - half, float(lo) + half


def histogram_lines(volume: Volume, bins: int = 16, width: int = 40) -> list[str]:
    """A text histogram (log-scaled bars) of the values, one line per bin."""
    counts, edges = histogram(volume, bins)
    logc = np.log1p(counts)
    scale = width / logc.max() if logc.max() > 0 else 0
    digits = _edge_digits(edges)
    column = max(12, digits + 6)
    return [
        f"{edges[i]:>{column}.{digits}g} .. {edges[i + 1]:<{column}.{digits}g} "
        f"{'#' * round(logc[i] * scale)}"
        for i in range(bins)
    ]


def _edge_digits(edges: np.ndarray) -> int:
    """Significant digits that tell the (bins + 1,) increasing `edges` apart: 5, more
    where the bins are narrow beside the values' magnitude (at most 17, float64's)."""
    step = float(edges[1] - edges[0])
    magnitude = float(np.abs(edges).max())
    if magnitude <= 0 or step <= 0:
        return 5
    return int(min(17, max(5, np.ceil(np.log10(magnitude / step)) + 2)))


@dataclass(frozen=True)
class VolumeInfo:
    """What ``isolume info`` says of a volume (`VolumeInfo.of`).

    Attributes:
        name: the volume's name; source: its file or synthetic spec.
        dims: (X, Y, Z) samples; voxels: their count.
        spacing, origin: (x, y, z) world units.
        placement: how the samples were placed ("" when nothing was said).
        value_range: (lo, hi) field units.
        counts: (16,) histogram counts; edges: (17,) their bin edges, field units.
        suggested: isovalues that show the structure (`suggest_isovalues`).
        histogram_lines: the text histogram, one line a bin.
    """

    name: str
    source: str
    dims: tuple[int, int, int]
    voxels: int
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float]
    placement: str
    value_range: tuple[float, float]
    counts: np.ndarray
    edges: np.ndarray
    suggested: tuple[float, ...]
    histogram_lines: tuple[str, ...]

    @classmethod
    def of(cls, volume: Volume) -> VolumeInfo:
        """The description of `volume`."""
        z, y, x = volume.data.shape
        counts, edges = histogram(volume)
        return cls(volume.name, volume.source, (x, y, z), int(volume.data.size),
                   tuple(volume.spacing), tuple(volume.origin), volume.placement,
                   tuple(float(v) for v in volume.value_range), counts, edges,
                   suggest_isovalues(volume), tuple(histogram_lines(volume)))

    def __str__(self) -> str:
        x, y, z = self.dims
        lo, hi = self.value_range
        lines = [f"volume     {self.source or self.name}",
                 f"dims       {x} x {y} x {z} (X x Y x Z), {self.voxels:,} voxels",
                 f"spacing    {', '.join(f'{s:g}' for s in self.spacing)}",
                 f"origin     {', '.join(f'{s:g}' for s in self.origin)}"]
        if self.placement:
            lines.append(f"placement  {self.placement}")
        lines += [f"range      {lo:g} .. {hi:g}", "histogram (log counts)"]
        lines += ["  " + line for line in self.histogram_lines]
        if self.suggested:
            lines.append(f"suggested isovalues: {', '.join(f'{s:.6g}' for s in self.suggested)}")
        else:
            lines.append("suggested isovalues: none (constant volume)")
        return "\n".join(lines)
