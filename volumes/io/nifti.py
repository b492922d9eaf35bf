"""NIfTI-1/2 volumes (``.nii``, ``.nii.gz``) via nibabel (extra ``nifti``): nibabel reads
the header, the samples are read here, no more of them than the header promises."""

from __future__ import annotations

import gzip
import math
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    RAS_TO_LPS,
    READ_ERRORS,
    Loaded,
    check_fits_in_memory,
    one_line,
    optional_module,
    read_at_most,
)


def load_nifti(path: Path) -> Loaded:
    """NIfTI via nibabel: [i, j, k] = [x, y, z] array -> (Z, Y, X).

    Spacing is the header zooms; the affine (nibabel's choice of sform and qform) maps
    voxels to RAS millimetres: its translation is the origin and its columns the axes'
    directions, both turned into LPS. The header's dims and datatype are checked (and an
    uncompressed file's size against them) before any sample is read; the samples are
    read, or inflated, at most one byte past the size they promise, and data that hold
    fewer or more bytes after vox_offset are refused.
    """
    nib = optional_module("nibabel", path)
    img = _open_header(nib, path)
    shape = _checked_shape(img.header.get_data_shape(), path)
    dtype, proxy = img.header.get_data_dtype(), img.dataobj
    scaled = (float(proxy.slope), float(proxy.inter)) != (1.0, 0.0)
    count = math.prod(shape)
    check_fits_in_memory(count * (dtype.itemsize + 8 * scaled), str(path),
                         f"dims {' '.join(map(str, shape))} {dtype}")
    raw = _read_samples(path, count * dtype.itemsize, int(proxy.offset))
    try:
        arr = raw.view(dtype).reshape(shape, order="F")
        arr = nib.volumeutils.apply_read_scaling(arr, proxy.slope, proxy.inter)
        zooms = tuple(float(z) for z in img.header.get_zooms()[:3])
        affine = np.asarray(img.affine, np.float64)
    except (nib.spatialimages.HeaderDataError, *READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable NIfTI file: {one_line(exc)}") from None
    return arr.transpose(2, 1, 0), zooms, affine[:3, 3], (affine[:3, :3], RAS_TO_LPS)


def _open_header(nib: ModuleType, path: Path) -> Any:
    """nibabel's image of `path`, its header read and checked (no sample read)."""
    try:
        with _raised_problems_unlogged(nib):
            return nib.load(str(path))
    except nib.spatialimages.HeaderDataError as exc:
        raise VolumeError(f"{path}: invalid NIfTI header: {one_line(exc)}; expected a "
                          "header nibabel reads (e.g. datatype 2 uint8, 4 int16, 16 "
                          "float32)") from None
    except (nib.filebasedimages.ImageFileError, *READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable NIfTI file: "
                          f"{_gzip_problem(path) or one_line(exc)}") from None


def _gzip_problem(path: Path) -> str | None:
    """Why the gzip data of a ``.gz`` file give no NIfTI header (348 bytes): cut short,
    or not gzip; None where they give one (or the file is no ``.gz``)."""
    if not path.name.lower().endswith(".gz"):
        return None
    try:
        with gzip.open(path, "rb") as stream:
            head = stream.read(348)
    except (OSError, EOFError, zlib.error) as exc:
        return f"its gzip data are damaged or cut short ({one_line(exc)})"
    if len(head) < 348:
        return (f"its gzip data end after {len(head)} bytes, before the 348 of a NIfTI "
                "header")
    return None


@contextmanager
def _raised_problems_unlogged(nib: ModuleType) -> Iterator[None]:
    """nibabel logs a header problem on stderr before raising it; the VolumeError says
    it, so the log line of a problem that raises is held back (the problems nibabel
    fixes, which do not raise, are still logged)."""
    globals_ = nib.imageglobals

    def lesser(record: Any) -> bool:
        return record.levelno < globals_.error_level

    globals_.logger.addFilter(lesser)
    try:
        yield
    finally:
        globals_.logger.removeFilter(lesser)


def _checked_shape(shape: tuple[int, ...], path: Path) -> tuple[int, int, int]:
    """The header's dims as (X, Y, Z): positive, trailing dims of 1 dropped, three left."""
    dims = tuple(int(d) for d in shape)
    if not dims or min(dims) < 1:
        raise VolumeError(f"{path}: NIfTI dims {dims} in the header; expected positive "
                          "sizes (x, y, z)")
    while len(dims) > 3 and dims[-1] == 1:
        dims = dims[:-1]
    if len(dims) != 3:
        raise VolumeError(
            f"{path}: expected a 3-D scalar NIfTI image (x, y, z), got shape {dims}"
        )
    return dims[0], dims[1], dims[2]


def _read_samples(path: Path, nbytes: int, offset: int) -> np.ndarray:
    """The `nbytes` bytes of samples from `offset` (in the inflated stream of a ``.gz``
    file) to the end of the data as a writable uint8 array; an uncompressed file's size
    is compared with them before anything is read, a compressed one is inflated one byte
    past them at most; data that hold fewer or more bytes are refused."""
    compressed = path.name.lower().endswith(".gz")
    try:
        with open(path, "rb") as plain:
            if compressed:
                with gzip.GzipFile(fileobj=plain) as stream:
                    stream.seek(offset)
                    buf, count = read_at_most(stream, nbytes)
            else:
                _check_file_size(path, plain.seek(0, 2), nbytes, offset)
                plain.seek(offset)
                buf, count = read_at_most(plain, nbytes)
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise VolumeError(f"{path}: corrupt gzip data ({one_line(exc)}); expected a "
                          "gzip-compressed NIfTI file") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None
    what = "decompressed bytes" if compressed else "bytes"
    if count < nbytes:
        raise VolumeError(f"{path}: expected {nbytes} {what} of samples from offset "
                          f"{offset}, the data ends after {count}: truncated, or the "
                          "header's dims or datatype are wrong")
    if count > nbytes:
        raise VolumeError(f"{path}: expected {nbytes} {what} of samples from offset "
                          f"{offset} to the end of the data, the data holds more: the "
                          "header's dims or datatype are wrong")
    return buf


def _check_file_size(path: Path, size: int, nbytes: int, offset: int) -> None:
    """Refuse an uncompressed file of `size` bytes that does not end with `nbytes` of
    samples from `offset` (the header's vox_offset): too short for them, or longer."""
    if size != offset + nbytes:
        problem = "truncated" if size < offset + nbytes else "bytes follow the samples"
        raise VolumeError(
            f"{path}: the header's dims and datatype need {nbytes} bytes of samples from "
            f"offset {offset} to the end of the file, the file holds "
            f"{max(0, size - offset)}: {problem}, or the header's dims, datatype or "
            "vox_offset are wrong")
