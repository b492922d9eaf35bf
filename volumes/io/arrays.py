"""NumPy volume files: ``.npy`` (a 3-D array indexed [z, y, x]) and ``.npz`` (array
``data`` or the only array, optional ``spacing`` and ``origin`` arrays, x, y, z order).

An array's header (shape and dtype) is read first and checked against the memory
available and against the bytes that follow it, so a header that lies about its size
costs no more than the bytes that are there."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    READ_ERRORS,
    Loaded,
    check_fits_in_memory,
    one_line,
    read_bounded,
)

_HEADER_READERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}
"""``.npy`` format versions read -> their header readers."""

Layout = tuple[tuple[int, ...], bool, np.dtype]
"""An array header's (shape, Fortran order, dtype)."""


def load_npy(path: Path, lazy: bool = False) -> Loaded:
    """``.npy`` holding a (Z, Y, X) array; with `lazy`, mapped read-only
    (``mmap_mode="r"``: nothing is read until sliced). The file must hold exactly the
    bytes its header's shape and dtype take."""
    where = str(path)
    _check_magic(path, b"\x93NUMPY", "a .npy array file")
    try:
        with open(path, "rb") as f:
            layout = _read_layout(f, where)
            start = f.tell()
            held = f.seek(0, 2) - start
        nbytes = _checked_nbytes(layout, where)
        _check_held(held, nbytes, layout, where, "the file")
        if not lazy:
            check_fits_in_memory(nbytes, where, _describe(layout))
        arr = np.load(path, mmap_mode="r" if lazy else None, allow_pickle=False)
    except VolumeError:
        raise
    except READ_ERRORS as exc:
        raise VolumeError(f"{path}: not a valid .npy array file: {one_line(exc)}") from None
    return _bool_as_uint8(arr), None, None, None


LATTICE_MEMBERS = ("values", "samples", "held", "meta")
"""Arrays that every illumination lattice file holds (`isolume.baking.lattice_file`)."""


def load_npz(path: Path) -> Loaded:
    """``.npz``: array ``data`` (or the only array) (Z, Y, X); optional ``spacing``, ``origin``."""
    _check_magic(path, b"PK", "a .npz (zip) archive")
    try:
        with zipfile.ZipFile(path) as archive:
            members = {name[:-4]: name for name in archive.namelist() if name.endswith(".npy")}
            key = _volume_key(path, list(members))
            arr = _read_member(archive, members[key], f"{path} [{key}]", volume=True)
            spacing = _optional_member(archive, members, "spacing", path)
            origin = _optional_member(archive, members, "origin", path)
    except VolumeError:
        raise
    except READ_ERRORS as exc:
        raise VolumeError(f"{path}: not a valid .npz archive (a zip of .npy arrays): "
                          f"{one_line(exc)}") from None
    return _bool_as_uint8(arr), spacing, origin, None


def _volume_key(path: Path, keys: list[str]) -> str:
    """The array of an ``.npz`` that holds the volume: ``data``, else the only one
    besides ``spacing`` and ``origin``."""
    candidates = [k for k in keys if k not in ("spacing", "origin")]
    if "data" in keys:
        return "data"
    if len(candidates) == 1:
        return candidates[0]
    if set(LATTICE_MEMBERS) <= set(keys):
        raise VolumeError(f"{path}: an illumination lattice (the .npz isolume bake writes), "
                          "not a volume: give it with --lattice, beside the volume it was "
                          "baked for")
    raise VolumeError(
        f"{path}: cannot tell which array is the volume among {keys}; "
        "expected an array named 'data' or a single array"
    )


def _optional_member(archive: zipfile.ZipFile, members: dict[str, str], key: str,
                     path: Path) -> np.ndarray | None:
    """Array `key` of the archive (``spacing``, ``origin``), or None where it has none."""
    return _read_member(archive, members[key], f"{path} [{key}]") if key in members else None


def _read_member(archive: zipfile.ZipFile, name: str, where: str,
                 volume: bool = False) -> np.ndarray:
    """The array of member `name`: its header read and checked against the size the zip
    records for it (and, for the `volume`, against memory) before its samples are
    inflated, at most one byte past what the header promises."""
    info = archive.getinfo(name)
    with archive.open(info) as stream:
        layout = _read_layout(stream, where)
        nbytes = _checked_nbytes(layout, where) if volume else _plain_nbytes(layout, where)
        _check_held(info.file_size - stream.tell(), nbytes, layout, where, "the member")
        check_fits_in_memory(nbytes, where, _describe(layout))
        buf = read_bounded(stream, nbytes, where,
                           compressed=info.compress_type != zipfile.ZIP_STORED)
    shape, fortran, dtype = layout
    return buf.view(dtype).reshape(shape, order="F" if fortran else "C")


def _read_layout(f: BinaryIO, where: str) -> Layout:
    """The (shape, Fortran order, dtype) of the ``.npy`` header `f` starts with; `f` is
    left where the samples start."""
    version = np.lib.format.read_magic(f)
    if version not in _HEADER_READERS:
        raise VolumeError(f"{where}: .npy format version {version[0]}.{version[1]}; "
                          "expected 1.0 or 2.0")
    shape, fortran, dtype = _HEADER_READERS[version](f)
    return tuple(int(n) for n in shape), bool(fortran), dtype


def _plain_nbytes(layout: Layout, where: str) -> int:
    """Bytes the samples of an array of numbers (of any shape) take."""
    shape, _, dtype = layout
    if dtype.hasobject:
        raise VolumeError(f"{where}: the array holds Python objects (dtype {dtype}); "
                          "expected numbers")
    return math.prod(shape) * dtype.itemsize


def _checked_nbytes(layout: Layout, where: str) -> int:
    """Bytes the samples of a 3-D array of numbers take."""
    shape = layout[0]
    if len(shape) != 3:
        raise VolumeError(f"{where}: expected a 3-D array indexed [z, y, x], got shape {shape}")
    return _plain_nbytes(layout, where)


def _check_held(held: int, nbytes: int, layout: Layout, where: str, holder: str) -> None:
    """Refuse `held` bytes of samples where the header's shape and dtype take `nbytes`."""
    if held == nbytes:
        return
    expected = f"expected {nbytes} bytes of samples for {_describe(layout)}"
    if held < nbytes:
        raise VolumeError(f"{where}: {expected}, {holder} holds only {held}: truncated, "
                          "or the header's shape or dtype are wrong")
    raise VolumeError(f"{where}: {expected}, {holder} holds {held}, {held - nbytes} more: "
                      "the header's shape or dtype do not match the data")


def _describe(layout: Layout) -> str:
    """``shape (Z, Y, X) uint8`` of a header, for messages."""
    shape, _, dtype = layout
    return f"shape {shape} {dtype}"


def _check_magic(path: Path, magic: bytes, what: str) -> None:
    """Refuse a file that does not start with ``magic`` (before numpy tries pickle)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(magic))
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None
    if head != magic:
        raise VolumeError(f"{path}: not {what}: it starts with {head!r}, expected {magic!r}")


def _bool_as_uint8(arr: np.ndarray) -> np.ndarray:
    """Booleans viewed as uint8 (no copy); other arrays as they are."""
    return arr.view(np.uint8) if arr.dtype == np.bool_ else arr
