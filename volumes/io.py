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
"""

from __future__ import annotations

import gzip
import importlib
import json
import operator
import os
import re
import struct
import zipfile
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, BinaryIO

import numpy as np

from isolume.volumes.core import Volume, VolumeError
from isolume.volumes.orientation import place

__all__ = ["RAW_DTYPES", "SUPPORTED_FORMATS", "load_file", "parse_raw_name"]

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

# Optional module -> (pip name, isolume extra).
_OPTIONAL = {
    "nrrd": ("pynrrd", "nrrd"),
    "nibabel": ("nibabel", "nifti"),
    "tifffile": ("tifffile", "tiff"),
    "pydicom": ("pydicom", "dicom"),
}

_RAW_NAME = re.compile(
    r"^(?P<stem>.+)_(?P<x>\d+)x(?P<y>\d+)x(?P<z>\d+)_(?P<dtype>[A-Za-z0-9]+)\.raw(?:\.gz)?$",
    re.IGNORECASE,
)

_TIFF_SUFFIXES = (".tif", ".tiff")

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

# Low-level failures that mean "this file is not what its name says"; turned into a
# one-line VolumeError by load_file as a last resort.
_READ_ERRORS = (
    OSError,
    EOFError,
    ValueError,
    zlib.error,
    struct.error,
    zipfile.BadZipFile,
    KeyError,
    IndexError,
    TypeError,
)

# (data [z, y, x], spacing xyz or None, origin xyz or None, orientation or None), the
# origin in the file's own frame; orientation: ((3, 3) columns = the direction of index
# axes x, y, z in that frame, (3,) signs that take the frame to LPS)
_Orientation = tuple[np.ndarray, np.ndarray]
_Loaded = tuple[np.ndarray, Sequence[float] | None, Sequence[float] | None,
                _Orientation | None]
LPS = np.ones(3)
"""Signs from a frame that already is LPS (DICOM, ITK's MetaImage)."""
RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])


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
    dims_xyz = _check_dims(dims, where, "given") if dims is not None else None
    raw_dtype = _resolve_dtype(dtype, where, "given") if dtype is not None else None
    byteorder = _check_endian(endian, where)

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
                    "for a headerless raw file pass --dims X Y Z and --dtype"
                )
        _check_readable(path)
    if kind != "raw" and (dims_xyz is not None or raw_dtype is not None or byteorder != "<"):
        raise VolumeError(
            f"{where}: --dims/--dtype/--endian only apply to raw files, but this is a "
            f"{_FORMAT_LABELS[kind]} input that records them itself"
        )

    try:
        if kind == "raw":
            data, spacing0, origin0, frame = _load_raw(path, dims_xyz, raw_dtype, byteorder)
            spacing0 = _manifest_spacing(path)
        else:
            data, spacing0, origin0, frame = _LOADERS[kind](path)
    except VolumeError:
        raise
    except _READ_ERRORS as exc:
        raise VolumeError(
            f"{where}: could not read this {_FORMAT_LABELS[kind]} input: {_one_line(exc)}"
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
    match = _match_raw_name(name)
    if match is None:
        return None
    stem, dims, dtype_name = match
    dims_xyz = _check_dims(dims, name, "in the file name")
    return stem, dims_xyz, _resolve_dtype(dtype_name, name, "in the file name")


# --------------------------------------------------------------------------- helpers


def _match_raw_name(name: str) -> tuple[str, tuple[int, int, int], str] | None:
    """Split ``stem_XxYxZ_dtype.raw[.gz]`` into (stem, (X, Y, Z), dtype name), or None."""
    match = _RAW_NAME.match(Path(name).name)
    if match is None:
        return None
    dims = (int(match["x"]), int(match["y"]), int(match["z"]))
    return match["stem"], dims, match["dtype"]


def _check_dims(dims: Any, where: str, how: str) -> tuple[int, int, int]:
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


def _resolve_dtype(name: Any, where: str, how: str) -> np.dtype:
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


def _check_endian(endian: str, where: str) -> str:
    """``"little"``/``"big"`` -> numpy byte-order character."""
    key = str(endian).strip().lower()
    if key not in ("little", "big"):
        raise VolumeError(f"{where}: endian must be 'little' or 'big', got {endian!r}")
    return "<" if key == "little" else ">"


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except OSError as exc:
        raise VolumeError(f"{path}: cannot access it: {_one_line(exc)}") from None


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
    match = _match_raw_name(path.name)
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


def _one_line(exc: BaseException) -> str:
    """Exception as ``Type: message`` on one line, at most ~200 characters."""
    text = " ".join(str(exc).split())
    if len(text) > 200:
        text = text[:197] + "..."
    name = type(exc).__name__
    if name == "error":  # zlib.error, struct.error
        name = f"{type(exc).__module__}.error"
    return f"{name}: {text}" if text else name


def _optional(module: str, path: Path) -> ModuleType:
    """Import an optional reader library or say which extra installs it."""
    pip_name, extra = _OPTIONAL[module]
    try:
        return importlib.import_module(module)
    except ImportError:
        raise VolumeError(
            f'reading {path} needs {pip_name}: pip install "isolume[{extra}]"'
        ) from None


def _check_readable(path: Path) -> None:
    """Open the file once so permission problems get a clear message."""
    try:
        with open(path, "rb") as f:
            f.read(1)
    except PermissionError:
        raise VolumeError(f"{path}: cannot read the file: permission denied") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {_one_line(exc)}") from None


def _read_bytes(path: Path) -> bytes:
    """Whole file contents, with OS errors as VolumeError."""
    try:
        with open(path, "rb") as f:
            return f.read()
    except PermissionError:
        raise VolumeError(f"{path}: cannot read the file: permission denied") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {_one_line(exc)}") from None


def _natural_key(name: str) -> tuple[tuple[Any, ...], str]:
    """Sort key putting ``slice2`` before ``slice10`` (digit runs compare as numbers)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts)), name


def _byte_count(dims_xyz: Sequence[int], dtype: np.dtype) -> tuple[int, str]:
    """Expected byte count of X*Y*Z samples, and the product written out."""
    x, y, z = dims_xyz
    return x * y * z * dtype.itemsize, f"{x}*{y}*{z}*{dtype.itemsize}"


# --------------------------------------------------------------------------- raw


def _load_raw(
    path: Path,
    dims: tuple[int, int, int] | None,
    dtype: np.dtype | None,
    byteorder: str,
) -> _Loaded:
    """Headerless samples, x fastest -> (Z, Y, X) array; no spacing or origin."""
    where = str(path)
    from_name = _match_raw_name(path.name)
    how = "given"
    if from_name is not None:
        if dims is None:
            dims = _check_dims(from_name[1], where, "in the file name")
        if dtype is None:
            dtype = _resolve_dtype(from_name[2], where, "in the file name")
        how = "in the file name"
    if dims is None or dtype is None:
        raise VolumeError(
            f"{where}: cannot tell the size and type of this raw file: name it "
            "NAME_XxYxZ_DTYPE.raw (e.g. skull_256x256x256_uint8.raw) or pass --dims X Y Z "
            f"and --dtype ({', '.join(RAW_DTYPES)})"
        )
    dtype = dtype.newbyteorder(byteorder)
    expected, product = _byte_count(dims, dtype)
    compressed = path.name.lower().endswith(".gz")
    buf, actual = _read_raw_samples(path, expected, compressed)
    if actual != expected:
        x, y, z = dims
        what = "decompressed bytes" if compressed else "bytes"
        problem = (
            f"only {actual} {what}: the file is truncated, or the dims/dtype {how} are wrong"
            if actual < expected
            else f"{actual} {what}: the dims/dtype {how} do not match the file size"
        )
        raise VolumeError(
            f"{where}: expected {product} = {expected} bytes for {x}x{y}x{z} "
            f"{dtype.name}, got {problem}"
        )
    x, y, z = dims
    return buf.view(dtype).reshape(z, y, x), None, None, None


def _read_raw_samples(path: Path, expected: int, compressed: bool) -> tuple[np.ndarray, int]:
    """Read ``expected`` bytes into a writable uint8 array; also count the file's total."""
    try:
        with open(path, "rb") as plain:
            if not compressed:
                return _read_counting(plain, expected)
            with gzip.GzipFile(fileobj=plain) as f:
                return _read_counting(f, expected)
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise VolumeError(
            f"{path}: corrupt gzip data ({_one_line(exc)}); expected a gzip-compressed raw file"
        ) from None
    except PermissionError:
        raise VolumeError(f"{path}: cannot read the file: permission denied") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {_one_line(exc)}") from None


def _read_counting(f: BinaryIO, nbytes: int) -> tuple[np.ndarray, int]:
    """First ``nbytes`` of a stream as uint8 (fewer at EOF) and the stream's total length."""
    buf = np.empty(nbytes, np.uint8)
    view = memoryview(buf)
    got = 0
    while got < nbytes:
        n = f.readinto(view[got:])
        if not n:
            break
        got += n
    total = got
    while chunk := f.read(1 << 20):
        total += len(chunk)
    return buf[:got], total


# --------------------------------------------------------------------------- NRRD


def _load_nrrd(path: Path) -> _Loaded:
    """NRRD / NHDR via pynrrd -> (Z, Y, X); spacing from space directions or spacings."""
    nrrd = _optional("nrrd", path)
    try:
        data, header = nrrd.read(str(path), index_order="C")
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the NRRD data: {_one_line(exc)}") from None
    except (nrrd.NRRDError, *_READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a valid NRRD file: {_one_line(exc)}") from None
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


# --------------------------------------------------------------------------- MetaImage


def _load_metaimage(path: Path) -> _Loaded:
    """MetaImage ``.mhd`` (separate data) / ``.mha`` (``LOCAL`` data) -> (Z, Y, X).

    ``TransformMatrix`` (or ``Rotation`` / ``Orientation``) gives the index axes' directions
    in LPS, one axis per three consecutive numbers as ITK writes it;
    ``AnatomicalOrientation`` alone is not used.
    """
    where = str(path)
    content = _read_bytes(path)
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
        payload, data_where = memoryview(_read_bytes(data_path)), str(data_path)

    expected, product = _byte_count(dims, dtype)
    header_size = 0
    if "headersize" in fields:
        header_size = int(_meta_numbers(fields, "HeaderSize", where, count=1)[0])
    if header_size > 0:
        payload = payload[header_size:]
    if compressed:
        payload = _meta_inflate(payload, fields, data_where, where)
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
    payload: memoryview, fields: dict[str, str], data_where: str, where: str
) -> bytes:
    """zlib (or gzip) inflate of ``CompressedData = True`` MetaImage data."""
    if "compresseddatasize" in fields:
        size = int(_meta_numbers(fields, "CompressedDataSize", where, count=1)[0])
        payload = payload[:size]
    try:
        return zlib.decompress(payload, zlib.MAX_WBITS | 32)
    except zlib.error as exc:
        raise VolumeError(
            f"{data_where}: corrupt compressed MetaImage data ({_one_line(exc)}); "
            "CompressedData = True expects zlib-deflated samples"
        ) from None


# --------------------------------------------------------------------------- NIfTI


def _load_nifti(path: Path) -> _Loaded:
    """NIfTI via nibabel: [i, j, k] = [x, y, z] array -> (Z, Y, X).

    Spacing is the header zooms; the affine (nibabel's choice of sform and qform) maps
    voxels to RAS millimetres: its translation is the origin and its columns the axes'
    directions, both turned into LPS.
    """
    nib = _optional("nibabel", path)
    try:
        img = nib.load(str(path))
        arr = np.asanyarray(img.dataobj)
        zooms = tuple(float(z) for z in img.header.get_zooms()[:3])
        affine = np.asarray(img.affine, np.float64)
    except (nib.filebasedimages.ImageFileError, *_READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable NIfTI file: {_one_line(exc)}") from None
    while arr.ndim > 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise VolumeError(
            f"{path}: expected a 3-D scalar NIfTI image (x, y, z), got shape {arr.shape}"
        )
    return arr.transpose(2, 1, 0), zooms, affine[:3, 3], (affine[:3, :3], RAS_TO_LPS)


# --------------------------------------------------------------------------- NumPy


def _load_npy(path: Path) -> _Loaded:
    """``.npy`` holding a (Z, Y, X) array."""
    _check_magic(path, b"\x93NUMPY", "a .npy array file")
    try:
        arr = np.load(path, allow_pickle=False)
    except _READ_ERRORS as exc:
        raise VolumeError(f"{path}: not a valid .npy array file: {_one_line(exc)}") from None
    return _check_numpy_array(arr, str(path)), None, None, None


def _load_npz(path: Path) -> _Loaded:
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
    except _READ_ERRORS as exc:
        raise VolumeError(f"{path}: not a valid .npz archive: {_one_line(exc)}") from None
    return _check_numpy_array(arr, f"{path} [{key}]"), spacing, origin, None


def _check_magic(path: Path, magic: bytes, what: str) -> None:
    """Refuse a file that does not start with ``magic`` (before numpy tries pickle)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(magic))
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {_one_line(exc)}") from None
    if head != magic:
        raise VolumeError(f"{path}: not {what}: it starts with {head!r}, expected {magic!r}")


def _check_numpy_array(arr: np.ndarray, where: str) -> np.ndarray:
    """A 3-D numeric array; booleans become uint8."""
    if arr.ndim != 3:
        raise VolumeError(f"{where}: expected a 3-D array indexed [z, y, x], got shape {arr.shape}")
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8)
    return arr


# --------------------------------------------------------------------------- TIFF


def _load_tiff_file(path: Path) -> _Loaded:
    """Multi-page TIFF (page = z slice) -> (Z, Y, X); ImageJ metadata give the spacing."""
    tifffile = _optional("tifffile", path)
    try:
        with tifffile.TiffFile(str(path)) as tif:
            arr = np.asarray(tif.series[0].asarray())
            if arr.ndim == 2 and len(tif.pages) > 1:
                pages = [np.asarray(page.asarray()) for page in tif.pages]
                shapes = {p.shape for p in pages}
                if len(shapes) != 1:
                    raise VolumeError(
                        f"{path}: TIFF pages differ in shape {sorted(shapes)}; expected one "
                        "(Y, X) shape for every z slice"
                    )
                arr = np.stack(pages)
            spacing = _imagej_spacing(tif)
    except VolumeError:
        raise
    except (tifffile.TiffFileError, *_READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable TIFF file: {_one_line(exc)}") from None
    if arr.ndim > 3:
        arr = arr.reshape([s for s in arr.shape if s != 1] or [1])
    if arr.ndim != 3:
        raise VolumeError(
            f"{path}: expected a grey-scale TIFF stack (one page per z slice), got an "
            f"array of shape {arr.shape}"
        )
    return arr, spacing, None, None


def _imagej_spacing(tif: Any) -> tuple[float, float, float] | None:
    """(x, y, z) voxel size from ImageJ metadata (resolution tags + ``spacing``), or None."""
    meta = tif.imagej_metadata
    if not meta:
        return None
    tags = tif.pages[0].tags

    def pixel_size(tag_name: str) -> float:
        tag = tags.get(tag_name)
        if tag is None:
            return 1.0
        num, den = tag.value
        return float(den) / float(num) if num else 1.0

    return (pixel_size("XResolution"), pixel_size("YResolution"), float(meta.get("spacing", 1.0)))


def _load_tiff_folder(path: Path, files: list[Path]) -> _Loaded:
    """Folder of 2-D TIFF slices (natural name order = z) -> (Z, Y, X)."""
    tifffile = _optional("tifffile", path)
    slices: list[np.ndarray] = []
    for file in files:
        _check_readable(file)
        try:
            img = np.asarray(tifffile.imread(str(file)))
        except (tifffile.TiffFileError, *_READ_ERRORS) as exc:
            raise VolumeError(f"{file}: not a readable TIFF slice: {_one_line(exc)}") from None
        if img.ndim > 2:
            img = img.reshape([s for s in img.shape if s != 1] or [1])
        if img.ndim != 2:
            raise VolumeError(
                f"{file}: expected a 2-D grey-scale slice (Y, X), got shape {img.shape}"
            )
        if slices and img.shape != slices[0].shape:
            raise VolumeError(
                f"{file}: slice shape {img.shape} differs from {files[0].name}'s "
                f"{slices[0].shape}; expected every slice the same size"
            )
        slices.append(img)
    return np.stack(slices), None, None, None


# --------------------------------------------------------------------------- DICOM


def _looks_like_dicom(file: Path) -> bool:
    """Cheap test (``.dcm`` name or ``DICM`` magic) used only when pydicom is missing."""
    if file.suffix.lower() == ".dcm":
        return True
    try:
        with open(file, "rb") as f:
            return f.read(132)[128:132] == b"DICM"
    except OSError:
        return False


def _read_dicom_series(path: Path, files: list[Path]) -> list[tuple[Path, Any]]:
    """Files that parse as DICOM with pixel data, largest SeriesInstanceUID only."""
    pydicom = _optional("pydicom", path)
    series: dict[str, list[tuple[Path, Any]]] = {}
    for file in files:
        try:
            ds = pydicom.dcmread(str(file))
        except Exception:  # anything that does not parse is not part of a series
            continue
        if "PixelData" not in ds:
            continue
        uid = str(ds.get("SeriesInstanceUID", ""))
        series.setdefault(uid, []).append((file, ds))
    if not series:
        return []
    return max(sorted(series.items()), key=lambda item: len(item[1]))[1]


def _ds_floats(ds: Any, keyword: str) -> np.ndarray | None:
    """A numeric DICOM attribute as a float64 array, or None when absent or empty."""
    value = ds.get(keyword)
    if value is None or value == "":
        return None
    try:
        arr = np.asarray(
            list(value) if isinstance(value, Sequence) and not isinstance(value, str) else [value],
            np.float64,
        )
    except (TypeError, ValueError):
        return None
    return arr if arr.size and np.isfinite(arr).all() else None


def _dicom_sort(items: list[tuple[Path, Any]]) -> tuple[list[tuple[Path, Any]], np.ndarray | None]:
    """Order slices along the slice normal; also return their sorted positions (mm) if known.

    Positions are ImagePositionPatient projected on row × column direction; without
    positions the slices go by InstanceNumber, then by file name.
    """
    positions = [_ds_floats(ds, "ImagePositionPatient") for _, ds in items]
    if all(p is not None and p.size == 3 for p in positions):
        iop = _ds_floats(items[0][1], "ImageOrientationPatient")
        normal = np.cross(iop[:3], iop[3:6]) if iop is not None and iop.size == 6 else None
        if normal is None or not np.linalg.norm(normal) > 0:
            normal = np.array([0.0, 0.0, 1.0])
        depth = np.array([float(np.dot(p, normal)) for p in positions])
        order = np.argsort(depth, kind="stable")
        return [items[i] for i in order], depth[order]
    numbers = [_ds_floats(ds, "InstanceNumber") for _, ds in items]
    if all(n is not None for n in numbers):
        order = np.argsort([float(n[0]) for n in numbers], kind="stable")
        return [items[i] for i in order], None
    return sorted(items, key=lambda item: _natural_key(item[0].name)), None


def _dicom_slice_step(
    path: Path, items: list[tuple[Path, Any]], depth: np.ndarray | None
) -> float | None:
    """Slice spacing (mm): the position step, else SpacingBetweenSlices / SliceThickness."""
    if depth is not None and depth.size > 1:
        steps = np.diff(depth)
        step = float(np.median(steps))
        if steps.min() <= 1e-6 * max(1.0, abs(step)):
            dup = int(np.count_nonzero(steps <= 1e-6 * max(1.0, abs(step))))
            raise VolumeError(
                f"{path}: {dup} DICOM slice(s) share a position with another slice; expected "
                "one slice per position (several echoes or phases mixed in one series?)"
            )
        if np.abs(steps - step).max() > 0.1 * step:
            raise VolumeError(
                f"{path}: DICOM slice positions are not evenly spaced (steps "
                f"{steps.min():.4g} to {steps.max():.4g} mm); expected a regular series "
                "(a slice missing?)"
            )
        return step
    ds = items[0][1]
    for keyword in ("SpacingBetweenSlices", "SliceThickness"):
        value = _ds_floats(ds, keyword)
        if value is not None and value[0] > 0:
            return float(value[0])
    return None


def _dicom_pixels(file: Path, ds: Any) -> np.ndarray:
    """One slice (rows = y, columns = x) with RescaleSlope/Intercept applied, float32."""
    try:
        pixels = np.asarray(ds.pixel_array)
    except Exception as exc:  # pydicom raises many kinds for undecodable pixel data
        raise VolumeError(
            f"{file}: cannot decode the DICOM pixel data ({_one_line(exc)}); compressed "
            "transfer syntaxes need pylibjpeg or gdcm"
        ) from None
    if pixels.ndim != 2:
        raise VolumeError(
            f"{file}: DICOM pixel data of shape {pixels.shape} (multi-frame or colour) is "
            "not supported; expected one 2-D grey-scale slice per file"
        )
    slope = _ds_floats(ds, "RescaleSlope")
    intercept = _ds_floats(ds, "RescaleIntercept")
    out = pixels.astype(np.float32)
    if slope is not None and slope[0] != 1.0:
        out *= np.float32(slope[0])
    if intercept is not None and intercept[0] != 0.0:
        out += np.float32(intercept[0])
    return out


def _load_dicom_folder(path: Path, items: list[tuple[Path, Any]]) -> _Loaded:
    """DICOM series -> (Z, Y, X) float32 (rescaled); spacing and origin in mm."""
    items, depth = _dicom_sort(items)
    first_file, first = items[0]
    slices = []
    for file, ds in items:
        pixels = _dicom_pixels(file, ds)
        if slices and pixels.shape != slices[0].shape:
            raise VolumeError(
                f"{file}: slice of {pixels.shape[0]} rows × {pixels.shape[1]} columns differs "
                f"from {first_file.name}'s {slices[0].shape}; expected one size per series"
            )
        slices.append(pixels)
    data = np.stack(slices)

    pixel_spacing = _ds_floats(first, "PixelSpacing")
    if pixel_spacing is None or pixel_spacing.size != 2:
        pixel_spacing = _ds_floats(first, "ImagerPixelSpacing")
    step = _dicom_slice_step(path, items, depth)
    spacing = None
    if (pixel_spacing is not None and pixel_spacing.size == 2) or step is not None:
        row_mm, col_mm = (
            (float(pixel_spacing[0]), float(pixel_spacing[1]))
            if pixel_spacing is not None and pixel_spacing.size == 2
            else (1.0, 1.0)
        )
        spacing = (col_mm, row_mm, step if step is not None else 1.0)
    position = _ds_floats(first, "ImagePositionPatient")
    origin = position if position is not None and position.size == 3 else None
    directions = _dicom_directions(first, depth)
    return data, spacing, origin, None if directions is None else (directions, LPS)


def _dicom_directions(first: Any, depth: np.ndarray | None) -> np.ndarray | None:
    """(3, 3) LPS directions of x (along a row), y (down a column) and z (the slice order:
    along the normal when positions sorted the slices), or None without
    ImageOrientationPatient."""
    iop = _ds_floats(first, "ImageOrientationPatient")
    if iop is None or iop.size != 6:
        return None
    row, col = iop[:3], iop[3:6]
    normal = np.cross(row, col)
    if depth is None or not np.linalg.norm(normal) > 0:
        return None  # slices not ordered along a known direction
    return np.stack([row, col, normal], axis=1)


# --------------------------------------------------------------------------- folders


def _load_folder(path: Path) -> _Loaded:
    """A folder of TIFF slices, else a DICOM series."""
    try:
        files = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    except PermissionError:
        raise VolumeError(f"{path}: cannot list the folder: permission denied") from None
    tiffs = [p for p in files if p.suffix.lower() in _TIFF_SUFFIXES]
    if tiffs:
        return _load_tiff_folder(path, sorted(tiffs, key=lambda p: _natural_key(p.name)))
    try:
        items = _read_dicom_series(path, files)
    except VolumeError:
        if any(_looks_like_dicom(f) for f in files):
            raise  # pydicom is missing and this looks like DICOM
        items = []
    if not items:
        shown = ", ".join(p.name for p in files[:3]) + (", ..." if len(files) > 3 else "")
        raise VolumeError(
            f"{path}: folder holds neither DICOM files with pixel data nor TIFF slices "
            f"({len(files)} file(s){': ' + shown if files else ''}); expected a DICOM series "
            "or *.tif/*.tiff slices"
        )
    return _load_dicom_folder(path, items)


_LOADERS: dict[str, Callable[[Path], _Loaded]] = {
    "nrrd": _load_nrrd,
    "metaimage": _load_metaimage,
    "nifti": _load_nifti,
    "npy": _load_npy,
    "npz": _load_npz,
    "tiff": _load_tiff_file,
    "folder": _load_folder,
}


def _manifest_spacing(path: Path) -> tuple[float, float, float] | None:
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
