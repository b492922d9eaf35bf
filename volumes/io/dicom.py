"""DICOM series (a folder of slices) via pydicom (extra ``dicom``): slices ordered along
their normal, rescaled to float32, spacing, origin and orientation in LPS millimetres."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import LPS, Loaded, natural_key, one_line, optional_module


def looks_like_dicom(file: Path) -> bool:
    """Cheap test (``.dcm`` name or ``DICM`` magic) used only when pydicom is missing."""
    if file.suffix.lower() == ".dcm":
        return True
    try:
        with open(file, "rb") as f:
            return f.read(132)[128:132] == b"DICM"
    except OSError:
        return False


def read_dicom_series(path: Path, files: list[Path]) -> list[tuple[Path, Any]]:
    """Files that parse as DICOM with pixel data, largest SeriesInstanceUID only."""
    pydicom = optional_module("pydicom", path)
    series: dict[str, list[tuple[Path, Any]]] = {}
    for file in files:
        try:
            ds = pydicom.dcmread(str(file))
        except Exception:  # anything that does not parse is not part of a series
            continue
        if "PixelData" not in ds:
            continue
        uid = str(ds.get("SeriesInstanceUID", ""))
        series.setdefault(uid, []).append((file, ds))
    if not series:
        return []
    return max(sorted(series.items()), key=lambda item: len(item[1]))[1]


def _ds_floats(ds: Any, keyword: str) -> np.ndarray | None:
    """A numeric DICOM attribute as a float64 array, or None when absent or empty."""
    value = ds.get(keyword)
    if value is None or value == "":
        return None
    try:
        arr = np.asarray(
            list(value) if isinstance(value, Sequence) and not isinstance(value, str) else [value],
            np.float64,
        )
    except (TypeError, ValueError):
        return None
    return arr if arr.size and np.isfinite(arr).all() else None


def _dicom_sort(items: list[tuple[Path, Any]]) -> tuple[list[tuple[Path, Any]], np.ndarray | None]:
    """Order slices along the slice normal; also return their sorted positions (mm) if known.

    Positions are ImagePositionPatient projected on row × column direction; without
    positions the slices go by InstanceNumber, then by file name.
    """
    positions = [_ds_floats(ds, "ImagePositionPatient") for _, ds in items]
    if all(p is not None and p.size == 3 for p in positions):
        iop = _ds_floats(items[0][1], "ImageOrientationPatient")
        normal = np.cross(iop[:3], iop[3:6]) if iop is not None and iop.size == 6 else None
        if normal is None or not np.linalg.norm(normal) > 0:
            normal = np.array([0.0, 0.0, 1.0])
        depth = np.array([float(np.dot(p, normal)) for p in positions])
        order = np.argsort(depth, kind="stable")
        return [items[i] for i in order], depth[order]
    numbers = [_ds_floats(ds, "InstanceNumber") for _, ds in items]
    if all(n is not None for n in numbers):
        order = np.argsort([float(n[0]) for n in numbers], kind="stable")
        return [items[i] for i in order], None
    return sorted(items, key=lambda item: natural_key(item[0].name)), None


def _dicom_slice_step(
    path: Path, items: list[tuple[Path, Any]], depth: np.ndarray | None
) -> float | None:
    """Slice spacing (mm): the position step, else SpacingBetweenSlices / SliceThickness."""
    if depth is not None and depth.size > 1:
        steps = np.diff(depth)
        step = float(np.median(steps))
        if steps.min() <= 1e-6 * max(1.0, abs(step)):
            dup = int(np.count_nonzero(steps <= 1e-6 * max(1.0, abs(step))))
            raise VolumeError(
                f"{path}: {dup} DICOM slice(s) share a position with another slice; expected "
                "one slice per position (several echoes or phases mixed in one series?)"
            )
        if np.abs(steps - step).max() > 0.1 * step:
            raise VolumeError(
                f"{path}: DICOM slice positions are not evenly spaced (steps "
                f"{steps.min():.4g} to {steps.max():.4g} mm); expected a regular series "
                "(a slice missing?)"
            )
        return step
    ds = items[0][1]
    for keyword in ("SpacingBetweenSlices", "SliceThickness"):
        value = _ds_floats(ds, keyword)
        if value is not None and value[0] > 0:
            return float(value[0])
    return None


def _dicom_pixels(file: Path, ds: Any) -> np.ndarray:
    """One slice (rows = y, columns = x) with RescaleSlope/Intercept applied, float32."""
    try:
        pixels = np.asarray(ds.pixel_array)
    except Exception as exc:  # pydicom raises many kinds for undecodable pixel data
        raise VolumeError(
            f"{file}: cannot decode the DICOM pixel data ({one_line(exc)}); compressed "
            "transfer syntaxes need pylibjpeg or gdcm"
        ) from None
    if pixels.ndim != 2:
        raise VolumeError(
            f"{file}: DICOM pixel data of shape {pixels.shape} (multi-frame or colour) is "
            "not supported; expected one 2-D grey-scale slice per file"
        )
    slope = _ds_floats(ds, "RescaleSlope")
    intercept = _ds_floats(ds, "RescaleIntercept")
    out = pixels.astype(np.float32)
    if slope is not None and slope[0] != 1.0:
        out *= np.float32(slope[0])
    if intercept is not None and intercept[0] != 0.0:
        out += np.float32(intercept[0])
    return out


def load_dicom_folder(path: Path, items: list[tuple[Path, Any]]) -> Loaded:
    """DICOM series -> (Z, Y, X) float32 (rescaled); spacing and origin in mm."""
    items, depth = _dicom_sort(items)
    first_file, first = items[0]
    slices = []
    for file, ds in items:
        pixels = _dicom_pixels(file, ds)
        if slices and pixels.shape != slices[0].shape:
            raise VolumeError(
                f"{file}: slice of {pixels.shape[0]} rows × {pixels.shape[1]} columns differs "
                f"from {first_file.name}'s {slices[0].shape}; expected one size per series"
            )
        slices.append(pixels)
    data = np.stack(slices)

    pixel_spacing = _ds_floats(first, "PixelSpacing")
    if pixel_spacing is None or pixel_spacing.size != 2:
        pixel_spacing = _ds_floats(first, "ImagerPixelSpacing")
    step = _dicom_slice_step(path, items, depth)
    spacing = None
    if (pixel_spacing is not None and pixel_spacing.size == 2) or step is not None:
        row_mm, col_mm = (
            (float(pixel_spacing[0]), float(pixel_spacing[1]))
            if pixel_spacing is not None and pixel_spacing.size == 2
            else (1.0, 1.0)
        )
        spacing = (col_mm, row_mm, step if step is not None else 1.0)
    position = _ds_floats(first, "ImagePositionPatient")
    origin = position if position is not None and position.size == 3 else None
    directions = _dicom_directions(first, depth)
    return data, spacing, origin, None if directions is None else (directions, LPS)


def _dicom_directions(first: Any, depth: np.ndarray | None) -> np.ndarray | None:
    """(3, 3) LPS directions of x (along a row), y (down a column) and z (the slice order:
    along the normal when positions sorted the slices), or None without
    ImageOrientationPatient."""
    iop = _ds_floats(first, "ImageOrientationPatient")
    if iop is None or iop.size != 6:
        return None
    row, col = iop[:3], iop[3:6]
    normal = np.cross(row, col)
    if depth is None or not np.linalg.norm(normal) > 0:
        return None  # slices not ordered along a known direction
    return np.stack([row, col, normal], axis=1)
