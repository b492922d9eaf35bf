"""The figures of ``isolume bench accuracy``: one picture against its path-traced reference,
and the summary over every case.

Every figure is taken over the *reference's* surface pixels (where its primary ray meets
the isosurface), on linear RGB radiance, so a pixel the picture leaves black (not drawn,
or drawn black) counts with its full error:

* relative RMSE: ``sqrt(mean((img − ref)²)) / mean(ref)`` over those pixels' RGB values
  (the charts' error, `app.charts.metrics`, there over the pixels both mark);
* the reference's own noise: ``sqrt(mean(stderr²)) / mean(ref)``, from its per-pixel
  standard errors; since E(img − ref)² = (img − exact)² + stderr² pixel by pixel, the
  error less that noise, ``sqrt(max(error² − noise², 0))``, estimates the error against
  the exact image;
* mean ratio: ``mean(img) / mean(ref)`` (1: the right light level overall);
* black fraction: the share of the pixels that are pure black (0 in every channel) in the
  picture where the reference is lit (luminance > 0);
* p99 pixel error: the 99th percentile over the pixels of ``sqrt(mean over RGB of
  (img − ref)²)``, divided by ``mean(ref)`` (reference noise included).

Arrays are flat in pixels (row-major from the top-left): radiance (N, 3), masks (N,).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

NOISE_RATIO = 0.25
"""The reference's noise may be at most this fraction of the error it measures."""
BLACK_LIMIT = 0.001
"""Cases whose black fraction exceeds this are counted in the summary (0.1 %)."""
RATIO_BAND = (0.97, 1.03)
"""Cases whose mean ratio falls outside this band are counted in the summary."""
TOTALS = ("paths", "bake_seconds", "lattice_bytes")
"""Row figures a mode's summary sums over its cases (a bake's: paths traced, wall time
and file bytes), to compare whole sweeps."""
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
"""Rec. 709 luminance weights of linear RGB."""


def relative_rmse(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """``sqrt(mean((img − ref)²)) / mean(ref)`` over the RGB values of the `mask` pixels.

    Args:
        image, reference: (N, 3) linear radiance; mask: (N,) bool, the reference's
            surface pixels.
    """
    diff = image[mask] - reference[mask]
    return float(np.sqrt(np.mean(diff * diff)) / np.mean(reference[mask]))


def reference_noise(reference: np.ndarray, stderr: np.ndarray, mask: np.ndarray) -> float:
    """``sqrt(mean(stderr²)) / mean(ref)`` over the RGB values of the `mask` pixels: the
    relative error the reference's own Monte Carlo noise adds (inf with < 2 samples).

    Args:
        reference, stderr: (N, 3) linear radiance and its standard error.
    """
    return float(np.sqrt(np.mean(stderr[mask] ** 2)) / np.mean(reference[mask]))


def less_noise(error: float, noise: float) -> float:
    """``sqrt(max(error² − noise², 0))``: the error with the reference's noise taken out
    in quadrature (0 when the noise explains all of it; NaN when the noise is unknown)."""
    if not math.isfinite(noise):
        return float("nan")
    return math.sqrt(max(error * error - noise * noise, 0.0))


def mean_ratio(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """``mean(img) / mean(ref)`` over the RGB values of the `mask` pixels."""
    return float(np.mean(image[mask]) / np.mean(reference[mask]))


def black_fraction(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """Share of the `mask` pixels that are 0 in every channel of `image` while the
    reference's luminance there is positive."""
    black = np.all(image[mask] == 0, axis=1) & (reference[mask] @ LUMINANCE > 0)
    return float(np.count_nonzero(black) / max(int(np.count_nonzero(mask)), 1))


def p99_error(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """99th percentile over the `mask` pixels of the RGB-RMS difference, over the mean
    reference radiance."""
    diff = image[mask] - reference[mask]
    per_pixel = np.sqrt(np.mean(diff * diff, axis=1))
    return float(np.percentile(per_pixel, 99) / np.mean(reference[mask]))


def case_figures(image: np.ndarray, image_mask: np.ndarray, reference: np.ndarray,
                 mask: np.ndarray, noise: float) -> dict[str, Any]:
    """Every figure of one picture against the reference (see the module docstring).

    Args:
        image: (N, 3) the picture's linear radiance (0 off its surface);
        image_mask: (N,) its surface pixels; reference: (N, 3); mask: (N,) the
            reference's surface pixels (at least one); noise: `reference_noise`.

    Returns:
        JSON-ready dict: rel_rmse, rel_rmse_less_noise, reference_noise,
        noise_rule_holds (noise ≤ `NOISE_RATIO` × the error less the noise), mean_ratio,
        black_fraction, p99_error, surface_pixels, mask_mismatch (pixels on the surface
        in one of the two only).
    """
    error = relative_rmse(image, reference, mask)
    corrected = less_noise(error, noise)
    return {
        "rel_rmse": error, "rel_rmse_less_noise": corrected, "reference_noise": noise,
        "noise_rule_holds": bool(noise <= NOISE_RATIO * corrected),
        "mean_ratio": mean_ratio(image, reference, mask),
        "black_fraction": black_fraction(image, reference, mask),
        "p99_error": p99_error(image, reference, mask),
        "surface_pixels": int(np.count_nonzero(mask)),
        "mask_mismatch": int(np.count_nonzero(image_mask != mask)),
    }


def next_spp(spp: int, noise: float, error: float, cap: int) -> int:
    """Samples per pixel that bring a reference of `spp` samples and relative `noise` to
    `NOISE_RATIO` × `error` (noise ∝ 1/√spp, 10 % to spare), at least twice and at most
    16 times `spp` (the error estimate is rough while the noise is large), and at most
    `cap`."""
    if error > 0 and math.isfinite(noise):
        needed = math.ceil(spp * (noise / (NOISE_RATIO * error)) ** 2 * 1.1)
    else:
        needed = 16 * spp
    return int(min(cap, max(2 * spp, min(needed, 16 * spp))))


def spread(values: list[float]) -> dict:
    """Median, 90th percentile and largest of `values` (None when empty)."""
    if not values:
        return {"median": None, "p90": None, "worst": None}
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
            "worst": float(max(values))}


def share(row: dict[str, Any], key: str) -> float:
    """A case's share of its bake's `key` (one of `TOTALS`): the whole where the case has a
    bake of its own, else the bake's over the cases it draws (``shared_by``)."""
    return row[key] / row.get("shared_by", 1)


def summarize(rows: list[dict[str, Any]], failures: list[dict[str, Any]]) -> dict[str, Any]:
    """The summary over measured `rows` (dicts of `case_figures` plus volume, iso, mode).

    Returns:
        JSON-ready: per mode the cases and the median, p90 and worst of the relative
        RMSE less the reference's noise and of the plain relative RMSE (with the worst
        case's volume and isovalue), and the sums of `TOTALS` where every case has them;
        the counts of cases with black fraction above `BLACK_LIMIT`, with mean ratio
        outside `RATIO_BAND`, where the reference's noise rule does not hold, and of
        failures.
    """
    modes = {}
    for mode in dict.fromkeys(row["mode"] for row in rows):
        mine = [row for row in rows if row["mode"] == mode]
        corrected = [r["rel_rmse_less_noise"] for r in mine
                     if math.isfinite(r["rel_rmse_less_noise"])]
        worst = max(mine, key=lambda r: r["rel_rmse_less_noise"]
                    if math.isfinite(r["rel_rmse_less_noise"]) else r["rel_rmse"])
        modes[mode] = {"cases": len(mine), "rel_rmse_less_noise": spread(corrected),
                       "rel_rmse": spread([r["rel_rmse"] for r in mine]),
                       "worst_case": {"volume": worst["volume"], "iso": worst["iso"]},
                       **{f"total_{key}": sum(share(r, key) for r in mine) for key in TOTALS
                          if all(r.get(key) is not None for r in mine)}}
    lo, hi = RATIO_BAND
    return {
        "modes": modes,
        "black_cases": sum(r["black_fraction"] > BLACK_LIMIT for r in rows),
        "ratio_cases": sum(not lo <= r["mean_ratio"] <= hi for r in rows),
        "noise_rule_unmet": sum(not r["noise_rule_holds"] for r in rows),
        "cases": len(rows), "failures": len(failures),
        "black_limit": BLACK_LIMIT, "ratio_band": list(RATIO_BAND),
    }
