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
    inflate_bounded,
    one_line,
    read_bytes,
)

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
    ``AnatomicalOrientation`` alone is not used.
    """
    where = str(path)
    content = read_bytes(path)
    fields, data_start = _parse_metaimage_header(content, where)
    dimsize = _meta_numbers(fields, "DimSize", where, required=True)
    ndims = int(_meta_numbers(fields, "NDims", where, count=1)[0]) if "ndims" in fields else 3
    if ndims != 3 or len(dimsize) != 3 or any(d != int(d) or d <= 0 for d in dimsize):
        raise VolumeError(
            f"{where}: expected a 3-D MetaImage (NDims = 3, DimSize = three positive "
            f"integers), got NDims = {ndims}, DimSize = {fields['dimsize']!r}"
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

    data_file = fields.get("elementdatafile", "")
    if data_file.upper() == "LOCAL":
        payload, data_where = memoryview(content)[data_start:], where
    elif data_file.upper().startswith("LIST") or "%" in data_file:
        raise VolumeError(
            f"{where}: ElementDataFile = {data_file!r} (a slice list or pattern) is not "
            "supported; expected LOCAL or one data file name"
        )
    else:
        data_path = path.parent / data_file
        if not data_path.is_file():
            raise VolumeError(
                f"{where}: ElementDataFile {data_file!r} not found (looked for {data_path})"
            )
        payload, data_where = memoryview(read_bytes(data_path)), str(data_path)

    expected, product = byte_count(dims, dtype)
    check_fits_in_memory(expected, data_where, f"DimSize {' '.join(map(str, dims))}")
    header_size = 0
    if "headersize" in fields:
        header_size = int(_meta_numbers(fields, "HeaderSize", where, count=1)[0])
    if header_size > 0:
        payload = payload[header_size:]
    if compressed:
        payload = _meta_inflate(payload, fields, data_where, where, expected)
    elif header_size == -1:  # MetaIO: the data are the last bytes of the file
        payload = payload[max(0, len(payload) - expected) :]
    if len(payload) != expected:
        x, y, z = dims
        raise VolumeError(
            f"{data_where}: expected {product} = {expected} bytes of {fields['elementtype']} "
            f"for DimSize {x} {y} {z}, got {len(payload)} bytes"
        )
    x, y, z = dims
    data = np.frombuffer(payload, dtype).reshape(z, y, x)
    return data, spacing, origin, frame


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


def _meta_inflate(
    payload: memoryview, fields: dict[str, str], data_where: str, where: str, expected: int
) -> bytes:
    """zlib (or gzip) inflate of ``CompressedData = True`` MetaImage data, stopped one
    byte past the `expected` bytes (`inflate_bounded`)."""
    if "compresseddatasize" in fields:
        size = int(_meta_numbers(fields, "CompressedDataSize", where, count=1)[0])
        payload = payload[:size]
    try:
        return inflate_bounded(payload, expected, zlib.MAX_WBITS | 32)
    except zlib.error as exc:
        raise VolumeError(
            f"{data_where}: corrupt compressed MetaImage data ({one_line(exc)}); "
            "CompressedData = True expects zlib-deflated samples"
        ) from None
