"""NumPy volume files: ``.npy`` (a 3-D array indexed [z, y, x]) and ``.npz`` (array
``data`` or the only array, optional ``spacing`` and ``origin`` arrays, x, y, z order)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import READ_ERRORS, Loaded, one_line


def load_npy(path: Path, lazy: bool = False) -> Loaded:
    """``.npy`` holding a (Z, Y, X) array; with `lazy`, mapped read-only
    (``mmap_mode="r"``: nothing is read until sliced)."""
    _check_magic(path, b"\x93NUMPY", "a .npy array file")
    try:
        arr = np.load(path, mmap_mode="r" if lazy else None, allow_pickle=False)
    except READ_ERRORS as exc:
        raise VolumeError(f"{path}: not a valid .npy array file: {one_line(exc)}") from None
    return _check_numpy_array(arr, str(path)), None, None, None


def load_npz(path: Path) -> Loaded:
    """``.npz``: array ``data`` (or the only array) (Z, Y, X); optional ``spacing``, ``origin``."""
    _check_magic(path, b"PK", "a .npz (zip) archive")
    try:
        with np.load(path, allow_pickle=False) as npz:
            keys = list(npz.files)
            candidates = [k for k in keys if k not in ("spacing", "origin")]
            if "data" in keys:
                key = "data"
            elif len(candidates) == 1:
                key = candidates[0]
            else:
                raise VolumeError(
                    f"{path}: cannot tell which array is the volume among {keys}; "
                    "expected an array named 'data' or a single array"
                )
            arr = npz[key]
            spacing = npz["spacing"] if "spacing" in keys else None
            origin = npz["origin"] if "origin" in keys else None
    except VolumeError:
        raise
    except READ_ERRORS as exc:
        raise VolumeError(f"{path}: not a valid .npz archive: {one_line(exc)}") from None
    return _check_numpy_array(arr, f"{path} [{key}]"), spacing, origin, None


def _check_magic(path: Path, magic: bytes, what: str) -> None:
    """Refuse a file that does not start with ``magic`` (before numpy tries pickle)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(magic))
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None
    if head != magic:
        raise VolumeError(f"{path}: not {what}: it starts with {head!r}, expected {magic!r}")


def _check_numpy_array(arr: np.ndarray, where: str) -> np.ndarray:
    """A 3-D numeric array; booleans are viewed as uint8 (no copy)."""
    if arr.ndim != 3:
        raise VolumeError(f"{where}: expected a 3-D array indexed [z, y, x], got shape {arr.shape}")
    if arr.dtype == np.bool_:
        arr = arr.view(np.uint8)
    return arr
