"""NRRD volumes (``.nrrd``, ``.nhdr`` with attached or detached data) via pynrrd (extra
``nrrd``): spacing, origin and orientation from the header."""

from __future__ import annotations

import bz2
import gzip
import math
from pathlib import Path
from typing import BinaryIO

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    INFLATE_CHUNK,
    READ_ERRORS,
    Loaded,
    check_fits_in_memory,
    one_line,
    optional_module,
    read_bounded,
)

_TYPES = {
    **dict.fromkeys(("signed char", "int8", "int8_t"), "i1"),
    **dict.fromkeys(("uchar", "unsigned char", "uint8", "uint8_t"), "u1"),
    **dict.fromkeys(("short", "short int", "signed short", "signed short int", "int16",
                     "int16_t"), "i2"),
    **dict.fromkeys(("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"),
                    "u2"),
    **dict.fromkeys(("int", "signed int", "int32", "int32_t"), "i4"),
    **dict.fromkeys(("uint", "unsigned int", "uint32", "uint32_t"), "u4"),
    **dict.fromkeys(("longlong", "long long", "long long int", "signed long long",
                     "signed long long int", "int64", "int64_t"), "i8"),
    **dict.fromkeys(("ulonglong", "unsigned long long", "unsigned long long int", "uint64",
                     "uint64_t"), "u8"),
    "float": "f4",
    "double": "f8",
}
"""NRRD ``type`` names -> numpy type codes (the NRRD format's list)."""


def load_nrrd(path: Path, lazy: bool = False) -> Loaded:
    """NRRD / NHDR -> (Z, Y, X); spacing from space directions or spacings.

    The header (pynrrd) says how many bytes the samples take; a header that needs more
    memory than the machine has is refused before any sample is read, and raw, gzip or
    bzip2 data (attached, or in one detached data file) are read (and decompressed) at
    most one byte past that size: data that hold fewer or more bytes are refused. Text
    encodings and lists of data files are read by pynrrd once the size is checked. With
    `lazy`, raw data (attached, or one detached data file) without skips is mapped
    instead (a read-only numpy memmap: nothing is read until sliced).
    """
    nrrd = optional_module("nrrd", path)
    try:
        with open(path, "rb") as fh:
            header = nrrd.read_header(fh)
            _check_directions(header, path)
            data = _bounded_data(header, fh, path, lazy)
        if data is None:
            data, header = nrrd.read(str(path), index_order="C")
    except VolumeError:
        raise
    except StopIteration:  # pynrrd's header reader finds no magic line
        raise VolumeError(f"{path}: not a valid NRRD file: it is empty; expected a "
                          "header starting with NRRD0001..NRRD0005") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the NRRD data: {one_line(exc)}") from None
    except (nrrd.NRRDError, *READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a valid NRRD file: {one_line(exc)}") from None
    data = np.asarray(data)
    if data.ndim != 3:
        sizes = tuple(int(s) for s in header.get("sizes", data.shape[::-1]))
        raise VolumeError(
            f"{path}: expected a 3-D scalar NRRD volume, got dimension {data.ndim} "
            f"with sizes {sizes} (fastest axis first)"
        )
    directions = _nrrd_directions(header)
    frame = None if directions is None else (directions, _nrrd_flips(header))
    return data, _nrrd_spacing(header), _nrrd_origin(header), frame


def _nrrd_spacing(header: dict) -> tuple[float, float, float] | None:
    """(3,) xyz voxel size: norms of the ``space directions`` rows, else ``spacings``."""
    directions = header.get("space directions")
    spacings = header.get("spacings")
    if directions is None and spacings is None:
        return None
    out = [1.0, 1.0, 1.0]
    for axis in range(3):  # header fields list the fastest (x) axis first
        row = None
        if directions is not None and len(directions) > axis:
            row = np.asarray(directions[axis], np.float64)
        if row is not None and row.size and np.isfinite(row).all():
            out[axis] = float(np.linalg.norm(row))
        elif spacings is not None and len(spacings) > axis and np.isfinite(spacings[axis]):
            out[axis] = abs(float(spacings[axis]))
    return (out[0], out[1], out[2])


_NRRD_SPACES = {  # NRRD space -> sign flips that take it to LPS (x, y, z)
    "left-posterior-superior": (1, 1, 1), "lps": (1, 1, 1),
    "right-anterior-superior": (-1, -1, 1), "ras": (-1, -1, 1),
    "left-anterior-superior": (1, -1, 1), "las": (1, -1, 1),
    "scanner-xyz": (1, 1, 1), "3d-right-handed": (1, 1, 1),
    "3d-left-handed": (-1, 1, 1),  # mirrored into a right-handed world
}


def _nrrd_flips(header: dict) -> np.ndarray:
    """(3,) signs that take the header's ``space`` to LPS (ones for other spaces)."""
    space = str(header.get("space", "")).strip().lower()
    return np.asarray(_NRRD_SPACES.get(space, (1, 1, 1)), np.float64)


def _check_directions(header: dict, path: Path) -> None:
    """Refuse ``space directions`` with a vector that is not all finite numbers (pynrrd
    reads ``none``, the NRRD word for an axis without one, as all NaN: that passes)."""
    for axis, row in enumerate(header.get("space directions", ())):
        vector = np.asarray(row, np.float64).reshape(-1)
        if not np.isnan(vector).all() and not np.isfinite(vector).all():
            raise VolumeError(
                f"{path}: space directions vector {axis + 1} = {tuple(vector.tolist())}; "
                "expected finite numbers (or none)")


def _nrrd_directions(header: dict) -> np.ndarray | None:
    """(3, 3) directions of the index axes (columns) in the header's space, from ``space
    directions`` (one row per axis), or None when the header gives none."""
    rows = header.get("space directions")
    if rows is None:
        return None
    d = np.asarray(rows, np.float64)
    if d.shape != (3, 3) or not np.isfinite(d).all():
        return None
    return d.T


def _nrrd_origin(header: dict) -> np.ndarray | None:
    """(3,) xyz ``space origin`` (else ``axis mins``), or None."""
    for key in ("space origin", "axis mins"):
        value = header.get(key)
        if value is None:
            continue
        arr = np.asarray(value, np.float64).reshape(-1)
        if arr.shape == (3,) and np.isfinite(arr).all():
            return arr
    return None


def _bounded_data(header: dict, fh: BinaryIO, path: Path, lazy: bool) -> np.ndarray | None:
    """(Z, Y, X) samples of raw, gzip or bzip2 data, attached (read after the header in
    `fh`) or in one detached data file, read and decompressed at most one byte past the
    size the header gives (`_read_encoded`), or with `lazy` raw data without skips
    mapped (`_mapped_data`); None where pynrrd must read them (text encodings, a list
    or pattern of data files). Samples read must fit in memory (`check_fits_in_memory`)."""
    sizes = [int(s) for s in np.atleast_1d(header.get("sizes", []))]
    if sizes and min(sizes) < 1:
        raise VolumeError(f"{path}: NRRD sizes {' '.join(map(str, sizes))}; expected "
                          "positive integers (fastest axis first)")
    kind = _TYPES.get(str(header.get("type", "")).strip().lower())
    if kind is None or not sizes:
        return None  # pynrrd's own message names what is wrong
    dtype = np.dtype(kind).newbyteorder(
        ">" if str(header.get("endian", "little")).lower() == "big" else "<")
    expected = math.prod(sizes) * dtype.itemsize
    encoding = _ENCODINGS.get(str(header.get("encoding", "raw")).lower())
    detached = _data_file(header)
    if detached:
        _check_data_file(path, detached)
    skips = any(k in header for k in ("line skip", "lineskip", "byte skip", "byteskip"))
    if lazy and encoding == "raw" and not skips and detached != "":
        source = (path, fh.tell()) if detached is None else (path.parent / detached, 0)
        return _mapped_data(*source, dtype, sizes, expected)
    check_fits_in_memory(expected, str(path), f"sizes {' '.join(map(str, sizes))} "
                         f"{header.get('type')}")
    if detached == "" or encoding is None:
        return None
    line_skip, byte_skip = _skips(header, path, encoding)
    if detached is None:
        buf = _read_encoded(fh, str(path), encoding, expected, line_skip, byte_skip)
    else:
        with open(path.parent / detached, "rb") as data:
            buf = _read_encoded(data, str(path.parent / detached), encoding, expected,
                                line_skip, byte_skip)
    return buf.view(dtype).reshape(sizes[::-1])


_ENCODINGS = {"raw": "raw", "gzip": "gzip", "gz": "gzip", "bzip2": "bzip2", "bz2": "bzip2"}
"""NRRD encodings read here (`_read_encoded`) -> their canonical names."""


def _skips(header: dict, path: Path, encoding: str) -> tuple[int, int]:
    """(line skip, byte skip) of the header: lines at least 0; bytes at least 0, or -1
    (the samples are the last bytes of the file) for raw data only."""
    line_skip = _skip_field(header, ("line skip", "lineskip"))
    byte_skip = _skip_field(header, ("byte skip", "byteskip"))
    lowest = -1 if encoding == "raw" else 0
    if line_skip < 0 or byte_skip < lowest:
        raise VolumeError(f"{path}: NRRD line skip {line_skip}, byte skip {byte_skip} with "
                          f"{encoding} encoding; expected numbers at least 0 (a byte skip "
                          "of -1 only with raw encoding)")
    return line_skip, byte_skip


def _skip_field(header: dict, keys: tuple[str, str]) -> int:
    """The integer of the first of `keys` in the header (0 when absent)."""
    return int(next((header[key] for key in keys if key in header), 0))


def _read_encoded(f: BinaryIO, where: str, encoding: str, expected: int, line_skip: int,
                  byte_skip: int) -> np.ndarray:
    """Exactly `expected` bytes of samples from `f` (positioned where the data start) as
    a writable uint8 array: `line_skip` lines of the file skipped first, then
    `byte_skip` bytes (of the decompressed stream for gzip and bzip2; -1: the raw
    samples are the file's last `expected` bytes). Data that hold fewer or more bytes
    are refused, having been read and decompressed one byte past `expected` at most
    (after the last bzip2 stream, bytes that are not bzip2 are left, as Python's `bz2`
    leaves them)."""
    _skip_lines(f, line_skip)
    if encoding == "raw":
        if byte_skip == -1:
            start, end = f.tell(), f.seek(0, 2)
            f.seek(max(start, end - expected))
        else:
            f.seek(byte_skip, 1)
        return read_bounded(f, expected, where, compressed=False)
    stream = gzip.GzipFile(fileobj=f) if encoding == "gzip" else bz2.BZ2File(f)
    with stream:
        _skip_bytes(stream, byte_skip)
        return read_bounded(stream, expected, where, compressed=True)


def _skip_lines(f: BinaryIO, count: int) -> None:
    """Read `count` lines of `f` (a chunk at a time: a long line costs no more)."""
    for _ in range(count):
        while (line := f.readline(INFLATE_CHUNK)) and not line.endswith(b"\n"):
            pass


def _skip_bytes(stream: BinaryIO, count: int) -> None:
    """Read and drop `count` bytes of `stream` (fewer where it ends), a chunk at a time."""
    while count > 0 and (dropped := len(stream.read(min(count, INFLATE_CHUNK)))):
        count -= dropped


def _data_file(header: dict) -> str | None:
    """The one detached data file a header names; None for attached data, "" for a
    list or a pattern of files."""
    name = header.get("data file", header.get("datafile"))
    if name is None:
        return None
    name = str(name).strip()
    return "" if name.upper().startswith("LIST") or "%" in name or " " in name else name


def _check_data_file(path: Path, name: str) -> None:
    """Refuse a detached data file `name` (beside the header `path`, or absolute) that
    is not there."""
    data_path = path.parent / name
    if not data_path.is_file():
        raise VolumeError(f"{path}: the detached data file {name!r} is missing (looked "
                          f"for {data_path}); expected it beside the header")


def _mapped_data(file: Path, offset: int, dtype: np.dtype, sizes: list[int],
                 expected: int) -> np.ndarray:
    """(Z, Y, X) read-only memmap of the `expected` bytes of raw samples from `offset` in
    `file`, whose length must be exactly that."""
    try:
        held = file.stat().st_size - offset
    except OSError as exc:
        raise VolumeError(f"{file}: cannot read the NRRD data: {one_line(exc)}") from None
    if held != expected:
        problem = "only " + str(held) if held < expected else "more"
        raise VolumeError(f"{file}: expected {expected} bytes of samples, the data holds "
                          f"{problem}: truncated, or the header's sizes or type are wrong")
    return np.memmap(file, dtype, mode="r", offset=offset, shape=tuple(sizes[::-1]))
