"""MetaImage volumes (``.mhd`` with a separate data file, ``.mha`` with ``LOCAL`` data,
zlib compression), parsed here without an extra library."""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    LPS,
    Loaded,
    byte_count,
    check_fits_in_memory,
    inflate_at_most,
    one_line,
    read_bounded,
)

_MAX_HEADER_BYTES = 1 << 20
"""Bytes of a MetaImage file searched for its header (the ElementDataFile line ends it);
headers are a few hundred."""

_MET_TYPES = {
    "MET_UCHAR": "u1",
    "MET_CHAR": "i1",
    "MET_USHORT": "u2",
    "MET_SHORT": "i2",
    "MET_UINT": "u4",
    "MET_INT": "i4",
    "MET_FLOAT": "f4",
    "MET_DOUBLE": "f8",
}


def load_metaimage(path: Path) -> Loaded:
    """MetaImage ``.mhd`` (separate data) / ``.mha`` (``LOCAL`` data) -> (Z, Y, X).

    ``TransformMatrix`` (or ``Rotation`` / ``Orientation``) gives the index axes' directions
    in LPS, one axis per three consecutive numbers as ITK writes it;
    ``AnatomicalOrientation`` alone is not used. The header (within the file's first
    `_MAX_HEADER_BYTES`) is read first; the samples' size (DimSize × ElementType) is
    checked against memory and, for uncompressed data, against the data file's size
    before any sample is read; compressed data are inflated one byte past it at most.
    """
    where = str(path)
    fields, data_start = _parse_metaimage_header(_read_head(path), where)
    dimsize = _meta_numbers(fields, "DimSize", where, required=True)
    ndims = _meta_numbers(fields, "NDims", where, count=1)[0] if "ndims" in fields else 3
    if ndims != 3 or len(dimsize) != 3 or any(not d.is_integer() or d <= 0 for d in dimsize):
        raise VolumeError(
            f"{where}: expected a 3-D MetaImage (NDims = 3, DimSize = three positive "
            f"integers), got NDims = {fields.get('ndims', '3')}, DimSize = "
            f"{fields['dimsize']!r}"
        )
    dims = (int(dimsize[0]), int(dimsize[1]), int(dimsize[2]))
    channels = fields.get("elementnumberofchannels", "1")
    if channels.strip() != "1":
        raise VolumeError(
            f"{where}: ElementNumberOfChannels = {channels!r}; expected 1 (scalar volume)"
        )
    dtype = _meta_dtype(fields, where)
    compressed = _meta_bool(fields, ("CompressedData",), where)
    spacing = _meta_first(fields, ("ElementSpacing", "ElementSize"), where)
    origin = _meta_first(fields, ("Offset", "Origin", "Position"), where)
    matrix = next((_meta_numbers(fields, key, where, count=9) for key in
                   ("TransformMatrix", "Rotation", "Orientation") if key.lower() in fields),
                  None)
    frame = None if matrix is None else (np.asarray(matrix, np.float64).reshape(3, 3).T, LPS)

    data_path, offset = _data_source(path, fields, data_start)
    expected, product = byte_count(dims, dtype)
    x, y, z = dims
    size = (f"{product} = {expected} bytes of {fields['elementtype']} for DimSize "
            f"{x} {y} {z}")
    header_size = _header_size(fields, where)
    if compressed:
        data = _read_compressed(data_path, offset + max(0, header_size), fields, where,
                                expected, size)
    else:
        data = _read_uncompressed(data_path, offset, header_size, expected, size)
    return data.view(dtype).reshape(z, y, x), spacing, origin, frame


def _read_head(path: Path) -> bytes:
    """The first `_MAX_HEADER_BYTES` of a MetaImage file (its header, and for ``LOCAL``
    data the first of them)."""
    try:
        with open(path, "rb") as f:
            return f.read(_MAX_HEADER_BYTES)
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None


def _data_source(path: Path, fields: dict[str, str], data_start: int) -> tuple[Path, int]:
    """(the file that holds the samples, where they start in it): `path` itself after
    its header for ``LOCAL``, else the one ElementDataFile beside it."""
    where = str(path)
    data_file = fields.get("elementdatafile", "")
    if data_file.upper() == "LOCAL":
        return path, data_start
    if data_file.upper().startswith("LIST") or "%" in data_file:
        raise VolumeError(
            f"{where}: ElementDataFile = {data_file!r} (a slice list or pattern) is not "
            "supported; expected LOCAL or one data file name"
        )
    data_path = path.parent / data_file
    if not data_path.is_file():
        raise VolumeError(
            f"{where}: ElementDataFile {data_file!r} not found (looked for {data_path})"
        )
    return data_path, 0


def _header_size(fields: dict[str, str], where: str) -> int:
    """HeaderSize: bytes to skip before the samples (0 when absent), or -1: the samples
    are the data file's last bytes (MetaIO's "compute it")."""
    if "headersize" not in fields:
        return 0
    value = _meta_numbers(fields, "HeaderSize", where, count=1)[0]
    if not value.is_integer() or value < -1:
        raise VolumeError(
            f"{where}: MetaImage HeaderSize = {fields['headersize']!r}; expected a whole "
            "number of bytes to skip, at least 0 (or -1: the data are the file's last bytes)"
        )
    return int(value)


def _read_uncompressed(data_path: Path, offset: int, header_size: int, expected: int,
                       size: str) -> np.ndarray:
    """The `expected` bytes of samples from `offset` (past `header_size` more, or the
    file's last ones for -1) of `data_path`, whose size is checked first."""
    data_where = str(data_path)
    try:
        with open(data_path, "rb") as f:
            end, start = f.seek(0, 2), offset + max(0, header_size)
            if header_size == -1 and end - start >= expected:  # MetaIO: the last bytes
                start = end - expected
            if end - start != expected:
                raise VolumeError(f"{data_where}: expected {size}, got {max(0, end - start)} "
                                  "bytes")
            check_fits_in_memory(expected, data_where, size)
            f.seek(start)
            return read_bounded(f, expected, data_where, compressed=False)
    except OSError as exc:
        raise VolumeError(f"{data_where}: cannot read the file: {one_line(exc)}") from None


def _read_compressed(data_path: Path, offset: int, fields: dict[str, str], where: str,
                     expected: int, size: str) -> np.ndarray:
    """The `expected` bytes of ``CompressedData = True`` samples from `offset` of
    `data_path` (at most CompressedDataSize bytes of them), inflated one byte past them
    at most (`inflate_at_most`); their stream must end the file."""
    data_where = str(data_path)
    check_fits_in_memory(expected, data_where, size)
    limit = None
    if "compresseddatasize" in fields:
        limit = _meta_numbers(fields, "CompressedDataSize", where, count=1)[0]
        if not limit.is_integer() or limit < 0:
            raise VolumeError(f"{where}: MetaImage CompressedDataSize = "
                              f"{fields['compresseddatasize']!r}; expected a number of bytes")
        limit = int(limit)
    try:
        with open(data_path, "rb") as f:
            held = f.seek(0, 2) - offset
            f.seek(offset)
            buf, count, used = inflate_at_most(f, expected, zlib.MAX_WBITS | 32, limit)
    except zlib.error as exc:
        raise VolumeError(
            f"{data_where}: corrupt compressed MetaImage data ({one_line(exc)}); "
            "CompressedData = True expects zlib-deflated samples"
        ) from None
    except OSError as exc:
        raise VolumeError(f"{data_where}: cannot read the file: {one_line(exc)}") from None
    if count != expected:
        more = " or more" if count > expected else ""  # inflating stops one byte past
        raise VolumeError(f"{data_where}: expected {size}, got {count} bytes{more} once "
                          "inflated")
    if used < held:
        raise VolumeError(f"{data_where}: expected the compressed samples to end the file, "
                          f"{held - used} bytes follow their {used}-byte stream: the header's "
                          "DimSize or ElementType are wrong, or the data are not one stream")
    return buf


def _parse_metaimage_header(content: bytes, where: str) -> tuple[dict[str, str], int]:
    """``Key = Value`` lines up to ``ElementDataFile`` -> (fields keyed lower case, data offset).

    The data offset is where ``LOCAL`` data start: just after the ElementDataFile line.
    """
    fields: dict[str, str] = {}
    pos = 0
    line_no = 0
    while pos < len(content):
        end = content.find(b"\n", pos)
        end = len(content) if end < 0 else end
        raw_line, pos = content[pos:end], end + 1
        line_no += 1
        try:
            line = raw_line.decode("ascii").strip()
        except UnicodeDecodeError:
            raise VolumeError(
                f"{where}: MetaImage header line {line_no} is not text; expected "
                "'Key = Value' lines ending with ElementDataFile"
            ) from None
        if not line:
            continue
        key, sep, value = line.partition("=")
        if not sep or not key.strip():
            raise VolumeError(
                f"{where}: MetaImage header line {line_no} {line[:80]!r} is not 'Key = Value'"
            )
        fields[key.strip().lower()] = value.strip()
        if key.strip().lower() == "elementdatafile":
            return fields, pos
    raise VolumeError(
        f"{where}: MetaImage header has no ElementDataFile line; expected it as the last "
        "header line"
    )


def _meta_numbers(
    fields: dict[str, str],
    key: str,
    where: str,
    *,
    count: int | None = None,
    required: bool = False,
) -> list[float]:
    """Whitespace-separated numbers of a MetaImage field (empty list when absent)."""
    text = fields.get(key.lower())
    if text is None:
        if required:
            raise VolumeError(f"{where}: MetaImage header has no {key}; expected {key} = X Y Z")
        return []
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    if not values or (count is not None and len(values) != count):
        expected = f"{count} number(s)" if count else "numbers"
        raise VolumeError(f"{where}: MetaImage {key} = {text!r}; expected {expected}")
    return values


def _meta_first(fields: dict[str, str], keys: Sequence[str], where: str) -> list[float] | None:
    """The first present of several synonymous 3-number fields, or None."""
    for key in keys:
        if key.lower() in fields:
            return _meta_numbers(fields, key, where, count=3)
    return None


def _meta_bool(fields: dict[str, str], keys: Sequence[str], where: str) -> bool:
    """A True/False MetaImage field (first present key), default False."""
    for key in keys:
        text = fields.get(key.lower())
        if text is None:
            continue
        if text.lower() in ("true", "1"):
            return True
        if text.lower() in ("false", "0"):
            return False
        raise VolumeError(f"{where}: MetaImage {key} = {text!r}; expected True or False")
    return False


def _meta_dtype(fields: dict[str, str], where: str) -> np.dtype:
    """ElementType and byte-order flag -> numpy dtype."""
    name = fields.get("elementtype")
    if name is None or name.upper() not in _MET_TYPES:
        raise VolumeError(
            f"{where}: MetaImage ElementType = {name!r}; expected one of {', '.join(_MET_TYPES)}"
        )
    msb = _meta_bool(fields, ("BinaryDataByteOrderMSB", "ElementByteOrderMSB"), where)
    return np.dtype(_MET_TYPES[name.upper()]).newbyteorder(">" if msb else "<")
