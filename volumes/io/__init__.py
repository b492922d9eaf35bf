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
* a ``.zarr`` folder (Zarr format 2 or 3): a 3-D array, or an OME-Zarr multiscale image
  whose ``level`` is picked, spacing and origin from its coordinate transformations —
  needs zarr (extra ``zarr``); see :mod:`volumes.io.zarr_folder`.

Every loader returns samples indexed ``[z, y, x]`` with spacing and origin in (x, y, z)
order, world units (millimetres for medical formats); see :mod:`volumes.core`.
Orientation is applied (:mod:`volumes.orientation`): NRRD ``space directions`` (in its
``space``), NIfTI's affine, MetaImage ``TransformMatrix`` and DICOM
``ImageOrientationPatient`` say where the index axes point, and the samples are reordered
so that they run along world +x, +y, +z of the patient's LPS frame (+z superior: a head
comes up upright); ``orientation=False`` keeps the file's index order instead. ``spacing``
and ``origin`` passed to :func:`load_file` override what a file says (along its index axes,
before the orientation is applied).

``crop`` (voxel index ranges) and ``downsample`` (block means) pick a part of the volume
as placed, in the same world place (:mod:`volumes.region`). Uncompressed raw files, NRRD
raw data and ``.npy`` files are then mapped (numpy memmap) and Zarr chunks read on
demand, so only the part is read, a slab of z planes at a time: memory holds the result
and one slab. Other formats are read whole, then cut.

Every bad input raises :class:`VolumeError` with a one-line message that names the file,
the offending value and what was expected.

Each format family has its module (`raw`, `nrrd`, `metaimage`, `nifti`, `arrays` for
``.npy``/``.npz``, `tiff`, `dicom`, `zarr_folder`; file reading with one-line errors in
`common`); this module picks the loader by extension or folder content, places the result
and cuts the part asked for (:func:`load_file`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import STORED_TYPES, Volume, VolumeError, checked_geometry
from isolume.volumes.io.arrays import load_npy, load_npz
from isolume.volumes.io.common import (
    READ_ERRORS,
    Loaded,
    check_fits_in_memory,
    check_readable,
    natural_key,
    one_line,
)
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
from isolume.volumes.io.zarr_folder import load_zarr, looks_like_zarr
from isolume.volumes.orientation import Placement, place
from isolume.volumes.region import (
    Crop,
    Region,
    check_factor,
    check_sample_type,
    join_placement,
    parse_crop,
    read_region,
    resolve_region,
)

__all__ = ["RAW_DTYPES", "SUPPORTED_FORMATS", "load_file", "parse_raw_name"]

#: Human-readable list of what :func:`load_file` reads, for messages and ``--help``.
SUPPORTED_FORMATS = (
    "NAME_XxYxZ_DTYPE.raw[.gz] (other raw files with --dims and --dtype), .nrrd, .nhdr, "
    ".mhd, .mha, .nii, .nii.gz, .npy, .npz, .tif/.tiff stacks, a folder of TIFF slices, "
    "a folder holding a DICOM series, .zarr folders (Zarr arrays, OME-Zarr images)"
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
    (".zarr", "zarr"),
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
    "zarr": "Zarr",
}


# --------------------------------------------------------------------------- public API


def load_file(
    path: str | os.PathLike[str],
    *,
    dims: tuple[int, int, int] | None = None,
    dtype: str | None = None,
    spacing: tuple[float, float, float] | None = None,
    origin: tuple[float, float, float] | None = None,
    endian: str = "little",
    orientation: bool = True,
    crop: str | Crop | None = None,
    downsample: int = 1,
    level: int | None = None,
) -> Volume:
    """Read a volume file or folder (see the module docstring for the formats).

    Args:
        path: file, or folder of TIFF slices / DICOM files, or ``.zarr`` folder.
        dims: (X, Y, Z) sample counts of a raw file; overrides the file name.
        dtype: sample type of a raw file (``uint8`` … ``float64``); overrides the file name.
        spacing: (3,) voxel size x, y, z, world units; overrides the file's header.
            Default: the header's, or (1, 1, 1).
        origin: (3,) world position x, y, z of voxel (0, 0, 0); overrides the header.
            Default: the header's, or (0, 0, 0).
        endian: byte order of a raw file, ``"little"`` (default) or ``"big"``.
        orientation: apply the header's orientation (see the module docstring).
        crop: ``X0:X1,Y0:Y1,Z0:Z1`` voxel index ranges (or a parsed `Crop`) of the
            volume as placed (after the orientation); None for all of it.
        downsample: block edge N ≥ 1: means of N³-voxel blocks (`volumes.region`).
        level: multiscale level of an OME-Zarr image (None: 0, the full resolution).

    Returns:
        A :class:`Volume` with (Z, Y, X) samples (`Volume`: their stored type, or
        float32), named after the file stem. With
        a crop or downsampling, raw, NRRD raw and ``.npy`` files are mapped and Zarr
        chunks read lazily, so only the part is read, slab by slab; other formats are
        read whole first.

    Raises:
        VolumeError: one line naming the file and what is wrong with it.
    """
    path = Path(path).expanduser()
    where = str(path)
    crop = parse_crop(crop) if isinstance(crop, str) else crop
    factor = check_factor(downsample)
    dims_xyz = check_dims(dims, where, "given") if dims is not None else None
    raw_dtype = resolve_dtype(dtype, where, "given") if dtype is not None else None
    byteorder = check_endian(endian, where)
    kind = _kind_of(path, dims_xyz is not None and raw_dtype is not None)
    if kind != "raw" and (dims_xyz is not None or raw_dtype is not None or byteorder != "<"):
        raise VolumeError(
            f"{where}: --dims/--dtype/--endian only apply to raw files, but this is a "
            f"{_FORMAT_LABELS[kind]} input that records them itself"
        )
    if level is not None and kind != "zarr":
        raise VolumeError(f"{where}: --level {level} only applies to OME-Zarr multiscale "
                          f"images (.zarr folders); this is a {_FORMAT_LABELS[kind]} input")

    lazy = crop is not None or factor > 1
    try:
        (data, spacing0, origin0, frame), note = _read(kind, path, dims_xyz, raw_dtype,
                                                      byteorder, lazy, level)
    except VolumeError:
        raise
    except READ_ERRORS as exc:
        raise VolumeError(
            f"{where}: could not read this {_FORMAT_LABELS[kind]} input: {one_line(exc)}"
        ) from exc

    spacing, origin = checked_geometry(_pick(spacing, spacing0, (1.0, 1.0, 1.0)),
                                       _pick(origin, origin0, (0.0, 0.0, 0.0)), where)
    placed, placement = _placed(data, spacing, origin, frame if orientation else None,
                                _placement_label(kind, frame, orientation, path), where)
    placement = join_placement(placement, note)
    if lazy or not isinstance(placed.data, np.ndarray):
        return _read_part(placed, crop, factor, path, placement)
    samples = placed.data
    if not samples.flags.writeable and samples.dtype.newbyteorder("=") in STORED_TYPES:
        samples = np.array(samples)  # Volume keeps these types as they are: its own copy
    return Volume(samples, spacing=placed.spacing, origin=placed.origin,
                  name=_volume_name(path), source=where, placement=placement)


def _kind_of(path: Path, raw_given: bool) -> str:
    """Format key of `path`: by what a folder holds, else by extension, else raw when
    `raw_given` (dims and dtype both given).

    Raises:
        VolumeError: no such path, an unknown extension, an unreadable file.
    """
    where = str(path)
    if not _exists(path):
        raise VolumeError(f"{where}: no such file or directory")
    if path.is_dir():
        return "zarr" if looks_like_zarr(path) else "folder"
    kind = _format_of(path)
    if kind is None:
        if not raw_given:
            suffix = path.suffix or "(none)"
            raise VolumeError(
                f"{where}: unknown file type {suffix!r}; supported: {SUPPORTED_FORMATS}; "
                "for a headerless raw file pass --dims X,Y,Z and --dtype"
            )
        kind = "raw"
    check_readable(path)
    return kind


def _read(kind: str, path: Path, dims_xyz, raw_dtype, byteorder: str, lazy: bool,
          level: int | None) -> tuple[Loaded, str]:
    """The loader's result for `kind`, and a note on what was taken ("" for most)."""
    if kind == "zarr":
        return load_zarr(path, level)
    if kind == "raw":
        data, _, origin0, frame = load_raw(path, dims_xyz, raw_dtype, byteorder, lazy)
        return (data, manifest_spacing(path), origin0, frame), ""
    loader = _LAZY_LOADERS.get(kind) if lazy else None
    return (loader(path, lazy=True) if loader else _LOADERS[kind](path)), ""


def _placement_label(kind: str, frame, orientation: bool, path: Path) -> str:
    """How the samples are placed in the world, for `isolume info`."""
    label = _FORMAT_LABELS[kind] if kind != "folder" else _folder_label(path)
    if frame is None:
        return f"as stored: the {label} input gives no orientation (--up AXIS turns it)"
    if not orientation:
        return "left out (orientation=False)"
    return f"{label} orientation, in LPS"


def _folder_label(path: Path) -> str:
    """What a folder volume was read as: TIFF slices where `_load_folder` found any
    (`_tiff_slices`), else a DICOM series."""
    return "TIFF" if _tiff_slices(_folder_files(path)) else "DICOM"


def _placed(data, spacing, origin, frame, label: str, where: str) -> tuple[Placement, str]:
    """(samples placed along world +x, +y, +z, the placement line): `frame` applied
    (a view of `data`, nothing read), or `data` as it is where `frame` is None."""
    if frame is None:
        return Placement(data, spacing, origin, 0.0), label
    directions, to_lps = frame
    placed = place(data, spacing, to_lps * np.asarray(origin), to_lps[:, None] * directions,
                   where)
    return placed, placed.describe(label)


def _read_part(placed: Placement, crop: Crop | None, factor: int, path: Path,
               placement: str) -> Volume:
    """The `crop` / `factor` part of the placed samples (a lazy array: memmap, Zarr),
    read slab by slab, as a Volume in the same world place. A crop of numbers of a type
    `Volume` does not keep (int32, float64, …) is read in that type, for `Volume` to say
    what float32 rounds of them."""
    where = str(path)
    data = placed.data
    check_sample_type(data.dtype, where)
    z, y, x = data.shape
    region = resolve_region((x, y, z), crop, factor, where)
    own = np.dtype(data.dtype)
    own_type = factor == 1 and own.kind in "iuf" and own.newbyteorder("=") not in STORED_TYPES
    check_fits_in_memory(region.nbytes // 4 * (4 + own.itemsize * own_type), where,
                         f"reading {' x '.join(map(str, region.shape_xyz))} voxels")
    samples = _cropped(data, region) if own_type else read_region(data, region)
    return Volume(samples, spacing=region.spacing(placed.spacing),
                  origin=region.origin(placed.spacing, placed.origin),
                  name=_volume_name(path), source=where,
                  placement=join_placement(placement, region.describe()))


def _cropped(data: Any, region: Region) -> np.ndarray:
    """The (Z', Y', X') samples of a `region` of factor 1 of the lazy `data`, in their
    own type."""
    (x0, y0, z0), (nx, ny, nz) = region.start, region.shape_xyz
    return np.array(data[z0:z0 + nz, y0:y0 + ny, x0:x0 + nx])


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
        name = path.name or path.resolve().name or str(path)
        return name[:-5] if name.lower().endswith(".zarr") and len(name) > 5 else name
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


def _folder_files(path: Path) -> list[Path]:
    """The visible regular files of the folder `path`, sorted by name."""
    try:
        return sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    except PermissionError:
        raise VolumeError(f"{path}: cannot list the folder: permission denied") from None


def _tiff_slices(files: list[Path]) -> list[Path]:
    """The TIFF slices among a folder's `files` (*.tif, *.tiff), in natural name order
    (the slices' z order)."""
    return sorted((p for p in files if p.suffix.lower() in TIFF_SUFFIXES),
                  key=lambda p: natural_key(p.name))


def _load_folder(path: Path) -> Loaded:
    """A folder of TIFF slices, else a DICOM series."""
    files = _folder_files(path)
    tiffs = _tiff_slices(files)
    if tiffs:
        return load_tiff_folder(path, tiffs)
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

_LAZY_LOADERS: dict[str, Callable[..., Loaded]] = {
    "nrrd": load_nrrd,
    "npy": load_npy,
}
"""Loaders that map the samples with ``lazy=True`` (raw files and Zarr folders too)."""
