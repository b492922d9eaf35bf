"""TIFF volumes via tifffile (extra ``tiff``): a multi-page stack (page = z) or a folder
of 2-D slices sorted naturally by name."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    READ_ERRORS,
    Loaded,
    check_readable,
    one_line,
    optional_module,
)

TIFF_SUFFIXES = (".tif", ".tiff")


def load_tiff_file(path: Path) -> Loaded:
    """Multi-page TIFF (page = z slice) -> (Z, Y, X); ImageJ metadata give the spacing."""
    tifffile = optional_module("tifffile", path)
    try:
        with tifffile.TiffFile(str(path)) as tif:
            arr = np.asarray(tif.series[0].asarray())
            if arr.ndim == 2 and len(tif.pages) > 1:
                pages = [np.asarray(page.asarray()) for page in tif.pages]
                shapes = {p.shape for p in pages}
                if len(shapes) != 1:
                    raise VolumeError(
                        f"{path}: TIFF pages differ in shape {sorted(shapes)}; expected one "
                        "(Y, X) shape for every z slice"
                    )
                arr = np.stack(pages)
            spacing = _imagej_spacing(tif)
    except VolumeError:
        raise
    except (tifffile.TiffFileError, *READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable TIFF file: {one_line(exc)}") from None
    if arr.ndim > 3:
        arr = arr.reshape([s for s in arr.shape if s != 1] or [1])
    if arr.ndim != 3:
        raise VolumeError(
            f"{path}: expected a grey-scale TIFF stack (one page per z slice), got an "
            f"array of shape {arr.shape}"
        )
    return arr, spacing, None, None


def _imagej_spacing(tif: Any) -> tuple[float, float, float] | None:
    """(x, y, z) voxel size from ImageJ metadata (resolution tags + ``spacing``), or None."""
    meta = tif.imagej_metadata
    if not meta:
        return None
    tags = tif.pages[0].tags

    def pixel_size(tag_name: str) -> float:
        tag = tags.get(tag_name)
        if tag is None:
            return 1.0
        num, den = tag.value
        return float(den) / float(num) if num else 1.0

    return (pixel_size("XResolution"), pixel_size("YResolution"), float(meta.get("spacing", 1.0)))


def load_tiff_folder(path: Path, files: list[Path]) -> Loaded:
    """Folder of 2-D TIFF slices (natural name order = z) -> (Z, Y, X)."""
    tifffile = optional_module("tifffile", path)
    slices: list[np.ndarray] = []
    for file in files:
        check_readable(file)
        try:
            img = np.asarray(tifffile.imread(str(file)))
        except (tifffile.TiffFileError, *READ_ERRORS) as exc:
            raise VolumeError(f"{file}: not a readable TIFF slice: {one_line(exc)}") from None
        if img.ndim > 2:
            img = img.reshape([s for s in img.shape if s != 1] or [1])
        if img.ndim != 2:
            raise VolumeError(
                f"{file}: expected a 2-D grey-scale slice (Y, X), got shape {img.shape}"
            )
        if slices and img.shape != slices[0].shape:
            raise VolumeError(
                f"{file}: slice shape {img.shape} differs from {files[0].name}'s "
                f"{slices[0].shape}; expected every slice the same size"
            )
        slices.append(img)
    return np.stack(slices), None, None, None
