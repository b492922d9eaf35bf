"""NRRD volumes (``.nrrd``, ``.nhdr`` with attached or detached data) via pynrrd (extra
``nrrd``): spacing, origin and orientation from the header."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import READ_ERRORS, Loaded, one_line, optional_module


def load_nrrd(path: Path) -> Loaded:
    """NRRD / NHDR via pynrrd -> (Z, Y, X); spacing from space directions or spacings."""
    nrrd = optional_module("nrrd", path)
    try:
        data, header = nrrd.read(str(path), index_order="C")
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
