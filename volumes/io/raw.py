"""Headerless raw volume files: ``.raw`` / ``.raw.gz`` samples, x fastest, named
``NAME_XxYxZ_DTYPE.raw[.gz]`` (the Open-SciVis convention) or read with given dims and
dtype; the voxel size from a ``manifest.json`` beside them."""

from __future__ import annotations

import gzip
import json
import operator
import re
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    Loaded,
    byte_count,
    check_fits_in_memory,
    one_line,
    read_at_most,
)

#: dtype names accepted in raw file names and for ``dtype=`` (little-endian on disk).
RAW_DTYPES: dict[str, str] = {
    "uint8": "u1",
    "int8": "i1",
    "uint16": "u2",
    "int16": "i2",
    "uint32": "u4",
    "int32": "i4",
    "float32": "f4",
    "float64": "f8",
    "float": "f4",
    "double": "f8",
}

_RAW_NAME = re.compile(
    r"^(?P<stem>.+)_(?P<x>\d+)x(?P<y>\d+)x(?P<z>\d+)_(?P<dtype>[A-Za-z0-9]+)\.raw(?:\.gz)?$",
    re.IGNORECASE,
)


def parse_raw_name(name: str) -> tuple[str, tuple[int, int, int], np.dtype] | None:
    """Parse the Open-SciVis raw naming convention ``stem_XxYxZ_dtype.raw[.gz]``.

    Args:
        name: a file name (a leading folder is ignored).

    Returns:
        ``(stem, (X, Y, Z), dtype)`` with the little-endian dtype, or None when the name
        does not follow the convention.

    Raises:
        VolumeError: the name follows the convention but its dtype is unknown or a
            dimension is zero.
    """
    match = match_raw_name(name)
    if match is None:
        return None
    stem, dims, dtype_name = match
    dims_xyz = check_dims(dims, name, "in the file name")
    return stem, dims_xyz, resolve_dtype(dtype_name, name, "in the file name")


def match_raw_name(name: str) -> tuple[str, tuple[int, int, int], str] | None:
    """Split ``stem_XxYxZ_dtype.raw[.gz]`` into (stem, (X, Y, Z), dtype name), or None."""
    match = _RAW_NAME.match(Path(name).name)
    if match is None:
        return None
    dims = (int(match["x"]), int(match["y"]), int(match["z"]))
    return match["stem"], dims, match["dtype"]


def check_dims(dims: Any, where: str, how: str) -> tuple[int, int, int]:
    """Validate (X, Y, Z) sample counts: three positive integers."""
    try:
        values = tuple(operator.index(v) for v in dims)
    except TypeError:
        raise VolumeError(
            f"{where}: dims {how} must be three integers X Y Z, got {dims!r}"
        ) from None
    if len(values) != 3:
        raise VolumeError(f"{where}: dims {how} must be three integers X Y Z, got {values}")
    if min(values) <= 0:
        raise VolumeError(f"{where}: dims {how} must all be positive (X Y Z), got {values}")
    return (values[0], values[1], values[2])


def resolve_dtype(name: Any, where: str, how: str) -> np.dtype:
    """Map a dtype name (``uint16``, ``float`` …) to a little-endian numpy dtype."""
    if isinstance(name, str):
        key = name.strip().lower()
    else:
        try:
            key = np.dtype(name).name
        except TypeError:
            key = repr(name)
    if key not in RAW_DTYPES:
        choices = ", ".join(RAW_DTYPES)
        raise VolumeError(f"{where}: unknown dtype {name!r} {how}; expected one of {choices}")
    return np.dtype(RAW_DTYPES[key]).newbyteorder("<")


def check_endian(endian: str, where: str) -> str:
    """``"little"``/``"big"`` -> numpy byte-order character."""
    key = str(endian).strip().lower()
    if key not in ("little", "big"):
        raise VolumeError(f"{where}: endian must be 'little' or 'big', got {endian!r}")
    return "<" if key == "little" else ">"


def load_raw(
    path: Path,
    dims: tuple[int, int, int] | None,
    dtype: np.dtype | None,
    byteorder: str,
    lazy: bool = False,
) -> Loaded:
    """Headerless samples, x fastest -> (Z, Y, X) array; no spacing or origin.

    With `lazy`, an uncompressed file is mapped (a read-only numpy memmap: nothing is
    read until sliced, and no memory check on the whole); compressed files are read whole.
    """
    where = str(path)
    from_name = match_raw_name(path.name)
    dims_named = dims is None and from_name is not None
    dtype_named = dtype is None and from_name is not None
    if dims_named:
        dims = check_dims(from_name[1], where, "in the file name")
    if dtype_named:
        dtype = resolve_dtype(from_name[2], where, "in the file name")
    how = _sizes_source(dims_named, dtype_named)
    if dims is None or dtype is None:
        raise VolumeError(
            f"{where}: cannot tell the size and type of this raw file: name it "
            "NAME_XxYxZ_DTYPE.raw (e.g. skull_256x256x256_uint8.raw) or pass --dims X,Y,Z "
            f"and --dtype ({', '.join(RAW_DTYPES)})"
        )
    dtype = dtype.newbyteorder(byteorder)
    expected, product = byte_count(dims, dtype)
    x, y, z = dims
    compressed = path.name.lower().endswith(".gz")
    size = f"{product} = {expected} bytes for {x}x{y}x{z} {dtype.name}"
    if not compressed:  # the file's size says it before anything is read
        _check_size(path, expected, size, how)
        if lazy:
            return np.memmap(path, dtype, mode="r", shape=(z, y, x)), None, None, None
    check_fits_in_memory(expected, where, f"{x}x{y}x{z} {dtype.name} ({how})")
    buf, actual = _read_raw_samples(path, expected, compressed)
    if actual != expected:
        what = "decompressed bytes" if compressed else "bytes"
        problem = (
            f"only {actual} {what}: the file is truncated, or {how} are wrong"
            if actual < expected
            else f"more {what}: {how} do not match the file"
        )
        raise VolumeError(f"{where}: expected {size}, got {problem}")
    return buf.view(dtype).reshape(z, y, x), None, None, None


def _sizes_source(dims_named: bool, dtype_named: bool) -> str:
    """Where a raw file's dims and dtype came from (its name, or ``--dims``/``--dtype``),
    as the subject of a message's "... are wrong"."""
    if dims_named and dtype_named:
        return "the dims/dtype in the file name"
    if not dims_named and not dtype_named:
        return "the --dims/--dtype given"
    dims = "the dims in the file name" if dims_named else "the --dims given"
    dtype = "the dtype in the file name" if dtype_named else "the --dtype given"
    return f"{dims} or {dtype}"


def _check_size(path: Path, expected: int, size: str, how: str) -> None:
    """Refuse an uncompressed raw file whose length is not the `expected` bytes."""
    try:
        actual = path.stat().st_size
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None
    if actual < expected:
        raise VolumeError(f"{path}: expected {size}, got only {actual} bytes: the file is "
                          f"truncated, or {how} are wrong")
    if actual > expected:
        raise VolumeError(f"{path}: expected {size}, got {actual} bytes: {how} do not "
                          "match the file size")


def _read_raw_samples(path: Path, expected: int, compressed: bool) -> tuple[np.ndarray, int]:
    """Read ``expected`` bytes into a writable uint8 array, and how many the stream
    holds: fewer, exactly, or ``expected + 1`` for more (it stops one byte past them)."""
    try:
        with open(path, "rb") as plain:
            if not compressed:
                return read_at_most(plain, expected)
            with gzip.GzipFile(fileobj=plain) as f:
                return read_at_most(f, expected)
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise VolumeError(
            f"{path}: corrupt gzip data ({one_line(exc)}); expected a gzip-compressed raw file"
        ) from None
    except PermissionError:
        raise VolumeError(f"{path}: cannot read the file: permission denied") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None


def manifest_spacing(path: Path) -> tuple[float, float, float] | None:
    """Voxel size (x, y, z) of a raw file from a ``manifest.json`` beside it, if it lists it.

    Raw files carry no header; collections of them (Open SciVis style) keep the voxel size
    in a JSON list of records ``{"file": NAME, "spacing_xyz": [x, y, z], ...}``. A missing
    or unreadable manifest, or no record for this file, leaves the spacing at (1, 1, 1).
    """
    manifest = path.parent / "manifest.json"
    if not manifest.is_file():
        return None
    try:
        records = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return None
    for record in records if isinstance(records, list) else []:
        if isinstance(record, dict) and record.get("file") == path.name:
            spacing = record.get("spacing_xyz")
            try:
                values = tuple(float(v) for v in spacing)
            except (TypeError, ValueError):
                return None
            ok = len(values) == 3 and all(np.isfinite(v) and v > 0 for v in values)
            return values if ok else None
    return None
