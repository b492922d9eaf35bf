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
    check_fits_in_memory,
    check_readable,
    one_line,
    optional_module,
)

TIFF_SUFFIXES = (".tif", ".tiff")


def load_tiff_file(path: Path) -> Loaded:
    """Multi-page TIFF (page = z slice) -> (Z, Y, X); ImageJ metadata give the spacing.

    The samples' size (the tags' shape × type) is checked against memory, and against
    what the file's stored bytes can decode to (`_check_size`), before any is decoded.
    """
    tifffile = optional_module("tifffile", path)
    what = "the image"
    try:
        with tifffile.TiffFile(str(path)) as tif:
            series, size = tif.series[0], tif.filehandle.size
            what = f"shape {tuple(series.shape)} {series.dtype}"
            _check_size(series, int(series.nbytes), 1, str(path), size, what)
            arr = np.asarray(series.asarray())
            if arr.ndim == 2 and len(tif.pages) > 1:
                arr = _stacked_pages(tif.pages, str(path), size)
            spacing = _imagej_spacing(tif)
    except VolumeError:
        raise
    except MemoryError:
        raise VolumeError(f"{path}: TIFF {what}: not enough memory to decode it; load a "
                          "smaller stack") from None
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


def _stacked_pages(pages: Any, where: str, size: int) -> np.ndarray:
    """(Z, Y, X) stack of the 2-D pages of a file whose first series is one page, their
    sizes checked first (`_check_size`: the pages and their stack)."""
    nbytes = sum(int(page.nbytes) for page in pages)
    _check_size(pages, nbytes, 2, where, size, f"{len(pages)} pages")
    arrays = [np.asarray(page.asarray()) for page in pages]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise VolumeError(f"{where}: TIFF pages differ in shape {sorted(shapes)}; expected "
                          "one (Y, X) shape for every z slice")
    return np.stack(arrays)


_MAX_EXPANSION = {1: 1, 8: 1032, 32946: 1032, 32773: 128}
"""TIFF Compression code -> the most bytes one stored byte decodes to: none (1),
Deflate (8, 32946: deflate's limit, 1032) and PackBits (32773: 128); other codecs are
not bounded here."""


def _check_size(pages: Any, nbytes: int, copies: int, where: str, size: int,
                what: str) -> None:
    """Refuse `nbytes` of samples (`what`: their shape and type, as the tags give them)
    that, `copies` held at once, need more memory than available, or that are more than
    the data of `pages` (a series, or a list of pages) stored in the file (of `size`
    bytes) decode to (`_decoded_bound`). Nothing is decoded."""
    check_fits_in_memory(copies * nbytes, where, f"TIFF {what}")
    bound = _decoded_bound(pages, size)
    if bound is not None and nbytes > bound:
        raise VolumeError(f"{where}: TIFF {what} needs {nbytes} bytes of samples, the "
                          f"file holds data for at most {bound}: truncated, or the image's "
                          "size tags are wrong")


def _decoded_bound(pages: Any, size: int) -> int | None:
    """The most bytes the data of `pages` stored in a file of `size` bytes decode to:
    for a series of uncompressed samples stored in one run (tifffile's ``dataoffset``,
    which it reads whole whatever the pages' strips say), the bytes from its start to
    the end of the file; else the parts of the pages' strips or tiles inside the file,
    times `_MAX_EXPANSION`; None where a page's compression has no bound here."""
    start = getattr(pages, "dataoffset", None)
    if start is not None:
        return max(0, size - start)
    bound = 0
    for page in pages:
        if page is None:
            continue
        expansion = _MAX_EXPANSION.get(int(page.compression))
        if expansion is None:
            return None
        segments = zip(page.dataoffsets, page.databytecounts, strict=False)
        stored = sum(max(0, min(count, size - offset)) for offset, count in segments)
        bound += expansion * stored
    return bound


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
    """Folder of 2-D TIFF slices (natural name order = z) -> (Z, Y, X).

    Each slice's shape (from its tags) is checked before it is decoded: the first's,
    times the number of files, against memory (`_check_size`: the slices and their
    stack), every other's against the first's.
    """
    tifffile = optional_module("tifffile", path)
    slices: list[np.ndarray] = []
    first: tuple[int, ...] = ()
    for file in files:
        check_readable(file)
        try:
            with tifffile.TiffFile(str(file)) as tif:
                series, size = tif.series[0], tif.filehandle.size
                shape = tuple(s for s in series.shape if s != 1) or (1,)
                if len(shape) != 2:
                    raise VolumeError(f"{file}: expected a 2-D grey-scale slice (Y, X), got "
                                      f"shape {tuple(series.shape)}")
                first = first or shape
                if shape != first:
                    raise VolumeError(f"{file}: slice shape {shape} differs from "
                                      f"{files[0].name}'s {first}; expected every slice "
                                      "the same size")
                what = f"slice shape {shape} {series.dtype}"
                copies = 2 * len(files) if not slices else 1
                _check_size(series, int(series.nbytes), copies, str(file), size, what)
                slices.append(np.asarray(series.asarray()).reshape(shape))
        except VolumeError:
            raise
        except MemoryError:
            raise VolumeError(f"{file}: TIFF slice shape {first}: not enough memory to "
                              "decode it with the slices before it") from None
        except (tifffile.TiffFileError, *READ_ERRORS) as exc:
            raise VolumeError(f"{file}: not a readable TIFF slice: {one_line(exc)}") from None
    return np.stack(slices), None, None, None
