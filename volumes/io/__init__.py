"""Load 3-D scalar volumes from files into :class:`volumes.core.Volume`.

Supported inputs (chosen by extension, or by what a folder holds):

* ``.raw`` / ``.raw.gz`` — headerless samples, x fastest (the Open-SciVis convention
  ``name_XxYxZ_dtype.raw[.gz]``, e.g. ``engine_zfp_256x256x128_uint8.raw.gz``, gives the
  dims and dtype; any other name needs ``dims`` and ``dtype``). Little-endian unless
  ``endian="big"``. A file with an unknown extension is read as raw when ``dims`` and
  ``dtype`` are both given.
* ``.nrrd`` / ``.nhdr`` (attached or detached data) — needs pynrrd (extra ``nrrd``).
* ``.mhd`` / ``.mha`` MetaImage (separate data file, ``LOCAL`` data, zlib compression) —
  parsed here, no extra library.
* ``.nii`` / ``.nii.gz`` NIfTI-1/2 — needs nibabel (extra ``nifti``).
* ``.npy`` (a 3-D array indexed [z, y, x]) and ``.npz`` (array ``data`` or the only array,
  optional ``spacing`` and ``origin`` arrays, x, y, z order).
* ``.tif`` / ``.tiff`` multi-page stack (page = z) or a folder of 2-D TIFF slices sorted
  naturally by name (``slice2`` before ``slice10``) — needs tifffile (extra ``tiff``).
* a folder holding a DICOM series — needs pydicom (extra ``dicom``).

Every loader returns samples indexed ``[z, y, x]`` with spacing and origin in (x, y, z)
order, world units (millimetres for medical formats); see :mod:`volumes.core`.
Orientation is applied (:mod:`volumes.orientation`): NRRD ``space directions`` (in its
``space``), NIfTI's affine, MetaImage ``TransformMatrix`` and DICOM
``ImageOrientationPatient`` say where the index axes point, and the samples are reordered
so that they run along world +x, +y, +z of the patient's LPS frame (+z superior: a head
comes up upright); ``orientation=False`` keeps the file's index order instead. ``spacing``
and ``origin`` passed to :func:`load_file` override what a file says (along its index axes,
before the orientation is applied).

Every bad input raises :class:`VolumeError` with a one-line message that names the file,
the offending value and what was expected.

Each format family has its module (`raw`, `nrrd`, `metaimage`, `nifti`, `arrays` for
``.npy``/``.npz``, `tiff`, `dicom`; file reading with one-line errors in `common`); this
module picks the loader by extension or folder content and places the result
(:func:`load_file`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import Volume, VolumeError
from isolume.volumes.io.arrays import load_npy, load_npz
from isolume.volumes.io.common import READ_ERRORS, Loaded, check_readable, natural_key, one_line
from isolume.volumes.io.dicom import load_dicom_folder, looks_like_dicom, read_dicom_series
from isolume.volumes.io.metaimage import load_metaimage
from isolume.volumes.io.nifti import load_nifti
from isolume.volumes.io.nrrd import load_nrrd
from isolume.volumes.io.raw import (
    RAW_DTYPES,
    check_dims,
    check_endian,
    load_raw,
    manifest_spacing,
    match_raw_name,
    parse_raw_name,
    resolve_dtype,
)
from isolume.volumes.io.tiff import TIFF_SUFFIXES, load_tiff_file, load_tiff_folder
from isolume.volumes.orientation import place

__all__ = ["RAW_DTYPES", "SUPPORTED_FORMATS", "load_file", "parse_raw_name"]

#: Human-readable list of what :func:`load_file` reads, for messages and ``--help``.
SUPPORTED_FORMATS = (
    "NAME_XxYxZ_DTYPE.raw[.gz] (other raw files with --dims and --dtype), .nrrd, .nhdr, "
    ".mhd, .mha, .nii, .nii.gz, .npy, .npz, .tif/.tiff stacks, a folder of TIFF slices, "
    "a folder holding a DICOM series"
)

# Extension (lower case, longest first where one ends another) -> format key.
_SUFFIXES: tuple[tuple[str, str], ...] = (
    (".raw.gz", "raw"),
    (".raw", "raw"),
    (".nrrd", "nrrd"),
    (".nhdr", "nrrd"),
    (".mhd", "metaimage"),
    (".mha", "metaimage"),
    (".nii.gz", "nifti"),
    (".nii", "nifti"),
    (".npy", "npy"),
    (".npz", "npz"),
    (".tiff", "tiff"),
    (".tif", "tiff"),
)

_FORMAT_LABELS = {
    "raw": "raw",
    "nrrd": "NRRD",
    "metaimage": "MetaImage",
    "nifti": "NIfTI",
    "npy": ".npy",
    "npz": ".npz",
    "tiff": "TIFF",
    "folder": "folder",
}


# --------------------------------------------------------------------------- public API


def load_file(
    path: str | os.PathLike,
    *,
    dims: tuple[int, int, int] | None = None,
    dtype: str | None = None,
    spacing: tuple[float, float, float] | None = None,
    origin: tuple[float, float, float] | None = None,
    endian: str = "little",
    orientation: bool = True,
) -> Volume:
    """Read a volume file or folder (see the module docstring for the formats).

    Args:
        path: file, or folder of TIFF slices / DICOM files.
        dims: (X, Y, Z) sample counts of a raw file; overrides the file name.
        dtype: sample type of a raw file (``uint8`` … ``float64``); overrides the file name.
        spacing: (3,) voxel size x, y, z, world units; overrides the file's header.
            Default: the header's, or (1, 1, 1).
        origin: (3,) world position x, y, z of voxel (0, 0, 0); overrides the header.
            Default: the header's, or (0, 0, 0).
        endian: byte order of a raw file, ``"little"`` (default) or ``"big"``.
        orientation: apply the header's orientation (see the module docstring).

    Returns:
        A :class:`Volume` with (Z, Y, X) float32 data, named after the file stem.

    Raises:
        VolumeError: one line naming the file and what is wrong with it.
    """
    path = Path(path).expanduser()
    where = str(path)
    dims_xyz = check_dims(dims, where, "given") if dims is not None else None
    raw_dtype = resolve_dtype(dtype, where, "given") if dtype is not None else None
    byteorder = check_endian(endian, where)

    if not _exists(path):
        raise VolumeError(f"{where}: no such file or directory")
    if path.is_dir():
        kind = "folder"
    else:
        kind = _format_of(path)
        if kind is None:
            if dims_xyz is not None and raw_dtype is not None:
                kind = "raw"
            else:
                suffix = path.suffix or "(none)"
                raise VolumeError(
                    f"{where}: unknown file type {suffix!r}; supported: {SUPPORTED_FORMATS}; "
                    "for a headerless raw file pass --dims X,Y,Z and --dtype"
                )
        check_readable(path)
    if kind != "raw" and (dims_xyz is not None or raw_dtype is not None or byteorder != "<"):
        raise VolumeError(
            f"{where}: --dims/--dtype/--endian only apply to raw files, but this is a "
            f"{_FORMAT_LABELS[kind]} input that records them itself"
        )

    try:
        if kind == "raw":
            data, spacing0, origin0, frame = load_raw(path, dims_xyz, raw_dtype, byteorder)
            spacing0 = manifest_spacing(path)
        else:
            data, spacing0, origin0, frame = _LOADERS[kind](path)
    except VolumeError:
        raise
    except READ_ERRORS as exc:
        raise VolumeError(
            f"{where}: could not read this {_FORMAT_LABELS[kind]} input: {one_line(exc)}"
        ) from exc

    if not data.flags.writeable and data.dtype == np.float32:
        data = np.array(data)  # Volume keeps native float32 as is; give it its own copy
    label = _FORMAT_LABELS[kind] if kind != "folder" else "DICOM"
    if frame is None or not orientation:
        why = "left out (orientation=False)" if frame is not None else (
            f"as stored: the {label} input gives no orientation (--up AXIS turns it)")
        return Volume(data, spacing=_pick(spacing, spacing0, (1.0, 1.0, 1.0)),
                      origin=_pick(origin, origin0, (0.0, 0.0, 0.0)), name=_volume_name(path),
                      source=where, placement=why)
    volume = Volume(data, spacing=_pick(spacing, spacing0, (1.0, 1.0, 1.0)),
                    origin=_pick(origin, origin0, (0.0, 0.0, 0.0)), source=where)
    directions, to_lps = frame
    placed = place(volume.data, volume.spacing, to_lps * np.asarray(volume.origin),
                   to_lps[:, None] * directions, where)
    return Volume(placed.data, spacing=placed.spacing, origin=placed.origin,
                  name=_volume_name(path), source=where,
                  placement=placed.describe(f"{label} orientation, in LPS"))


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except OSError as exc:
        raise VolumeError(f"{path}: cannot access it: {one_line(exc)}") from None


def _format_of(path: Path) -> str | None:
    """Format key from the file extension (case-insensitive), or None."""
    lower = path.name.lower()
    for suffix, kind in _SUFFIXES:
        if lower.endswith(suffix):
            return kind
    return None


def _volume_name(path: Path) -> str:
    """File stem without the format extension or the raw ``_XxYxZ_dtype`` suffix."""
    if path.is_dir():
        return path.name or path.resolve().name or str(path)
    match = match_raw_name(path.name)
    if match is not None:
        return match[0]
    lower = path.name.lower()
    for suffix, _ in _SUFFIXES:
        if lower.endswith(suffix) and len(lower) > len(suffix):
            return path.name[: -len(suffix)]
    return path.stem or path.name


def _pick(override: Any, from_file: Any, default: tuple[float, float, float]) -> Any:
    """Caller's value, else the file's, else the default."""
    if override is not None:
        return override
    if from_file is not None:
        return from_file
    return default


# --------------------------------------------------------------------------- folders


def _load_folder(path: Path) -> Loaded:
    """A folder of TIFF slices, else a DICOM series."""
    try:
        files = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    except PermissionError:
        raise VolumeError(f"{path}: cannot list the folder: permission denied") from None
    tiffs = [p for p in files if p.suffix.lower() in TIFF_SUFFIXES]
    if tiffs:
        return load_tiff_folder(path, sorted(tiffs, key=lambda p: natural_key(p.name)))
    try:
        items = read_dicom_series(path, files)
    except VolumeError:
        if any(looks_like_dicom(f) for f in files):
            raise  # pydicom is missing and this looks like DICOM
        items = []
    if not items:
        shown = ", ".join(p.name for p in files[:3]) + (", ..." if len(files) > 3 else "")
        raise VolumeError(
            f"{path}: folder holds neither DICOM files with pixel data nor TIFF slices "
            f"({len(files)} file(s){': ' + shown if files else ''}); expected a DICOM series "
            "or *.tif/*.tiff slices"
        )
    return load_dicom_folder(path, items)


_LOADERS: dict[str, Callable[[Path], Loaded]] = {
    "nrrd": load_nrrd,
    "metaimage": load_metaimage,
    "nifti": load_nifti,
    "npy": load_npy,
    "npz": load_npz,
    "tiff": load_tiff_file,
    "folder": _load_folder,
}
