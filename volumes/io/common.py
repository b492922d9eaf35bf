"""What every volume file loader shares: the loaders' result type, the frames they name,
the low-level errors that mean a bad file, optional reader libraries, and file reading
with one-line errors."""

from __future__ import annotations

import importlib
import os
import re
import stat
import struct
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, BinaryIO

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.cores import cgroup_file

OPTIONAL_MODULES = {
    "nrrd": ("pynrrd", "nrrd"),
    "nibabel": ("nibabel", "nifti"),
    "tifffile": ("tifffile", "tiff"),
    "pydicom": ("pydicom", "dicom"),
    "zarr": ("zarr", "zarr"),
}
"""Optional reader module → (pip name, isolume extra)."""

READ_ERRORS = (
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
"""Low-level failures that mean "this file is not what its name says"; turned into a
one-line VolumeError by `load_file` as a last resort."""

INFLATE_CHUNK = 1 << 20
"""Bytes of compressed input read, and of inflated output made, at a time by
`inflate_at_most`."""

Orientation = tuple[np.ndarray, np.ndarray]
"""((3, 3) columns: the directions of index axes x, y, z in the file's frame, (3,) signs
that take that frame to LPS)."""
Loaded = tuple[np.ndarray, Sequence[float] | None, Sequence[float] | None,
               Orientation | None]
"""What a loader returns: (data [z, y, x], spacing xyz or None, origin xyz or None in the
file's own frame, `Orientation` or None)."""
LPS = np.ones(3)
"""Signs from a frame that already is LPS (DICOM, ITK's MetaImage)."""
RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])
"""Signs from RAS (NIfTI's frame) to LPS."""


def one_line(exc: BaseException) -> str:
    """Exception as ``Type: message`` on one line, at most ~200 characters."""
    text = " ".join(str(exc).split())
    if len(text) > 200:
        text = text[:197] + "..."
    name = type(exc).__name__
    if name == "error":  # zlib.error, struct.error
        name = f"{type(exc).__module__}.error"
    return f"{name}: {text}" if text else name


def optional_module(module: str, path: Path) -> ModuleType:
    """Import an optional reader library or say which extra installs it."""
    pip_name, extra = OPTIONAL_MODULES[module]
    try:
        return importlib.import_module(module)
    except ImportError:
        raise VolumeError(
            f'reading {path} needs {pip_name}: pip install "isolume[{extra}]"'
        ) from None


_NOT_REGULAR = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)
"""Tests of a file's mode, and what they name, for `check_readable`'s message."""


def check_readable(path: Path) -> None:
    """Refuse what is not a regular file (reading a FIFO would wait for a writer, a
    device never ends), then open the file once so permission problems get a clear
    message."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _NOT_REGULAR if test(mode)), "not a regular file")
        raise VolumeError(f"{path}: this is {kind}, not a regular file; expected a volume "
                          "file")
    try:
        with open(path, "rb") as f:
            f.read(1)
    except PermissionError:
        raise VolumeError(f"{path}: cannot read the file: permission denied") from None
    except OSError as exc:
        raise VolumeError(f"{path}: cannot read the file: {one_line(exc)}") from None


def natural_key(name: str) -> tuple[tuple[Any, ...], str]:
    """Sort key putting ``slice2`` before ``slice10`` (digit runs compare as numbers)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts)), name


def byte_count(dims_xyz: Sequence[int], dtype: np.dtype) -> tuple[int, str]:
    """Expected byte count of X*Y*Z samples, and the product written out."""
    x, y, z = dims_xyz
    return x * y * z * dtype.itemsize, f"{x}*{y}*{z}*{dtype.itemsize}"


def available_memory() -> int | None:
    """Bytes of memory this machine can still give a process (Linux ``MemAvailable``,
    else physical memory), no more than its cgroup's limit leaves (a container's:
    `cgroup_memory_left`), or None where none of them is known."""
    known = [left for left in (_machine_memory(), cgroup_memory_left()) if left is not None]
    return min(known) if known else None


def _machine_memory() -> int | None:
    """Linux ``MemAvailable`` in bytes, else the physical memory, else None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def cgroup_memory_left() -> int | None:
    """Bytes this process's cgroup v2 may still use (``memory.max`` less
    ``memory.current``, at least 0), or None where it has no limit or none is readable."""
    limit, current = cgroup_file("memory.max"), cgroup_file("memory.current")
    try:
        if limit is None or current is None or limit.strip() == "max":
            return None
        return max(0, int(limit) - int(current))
    except ValueError:
        return None


def check_fits_in_memory(nbytes: int, where: str, what: str) -> None:
    """Refuse, before anything is read, samples whose `nbytes` (as the header or the file
    name gives them: `what`) exceed the memory this machine has available."""
    free = available_memory()
    if free is not None and nbytes > free:
        raise VolumeError(
            f"{where}: {what} needs {nbytes / 1e9:.3g} GB of samples, more than the "
            f"{free / 1e9:.3g} GB of memory available; load a part of it (--crop "
            "X0:X1,Y0:Y1,Z0:Z1, --downsample N; read without the whole file from raw, NRRD "
            "raw, .npy and Zarr)"
        )


def read_at_most(f: BinaryIO, nbytes: int) -> tuple[np.ndarray, int]:
    """First `nbytes` of a stream as a writable uint8 array (fewer at its end) and the
    stream's length counted up to ``nbytes + 1``: a stream that holds more is not read
    (nor decompressed) further, so a file that lies about its size, or a decompression
    bomb, costs no more memory than the samples promised."""
    buf = np.empty(nbytes, np.uint8)
    view = memoryview(buf)
    got = 0
    while got < nbytes:
        n = f.readinto(view[got:])
        if not n:
            break
        got += n
    return buf[:got], got + (got == nbytes and len(f.read(1)))


def read_bounded(f: BinaryIO, nbytes: int, where: str, compressed: bool) -> np.ndarray:
    """Exactly `nbytes` bytes of a stream (`read_at_most`); refuses a stream that holds
    fewer, or more."""
    what = "decompressed bytes" if compressed else "bytes"
    buf, count = read_at_most(f, nbytes)
    if count < nbytes:
        raise VolumeError(f"{where}: expected {nbytes} {what} of samples, the data ends "
                          f"after {count}: truncated, or the header's sizes are wrong")
    if count > nbytes:
        raise VolumeError(f"{where}: expected {nbytes} {what} of samples, the data holds "
                          "more: the header's sizes or type are wrong")
    return buf


def inflate_at_most(f: BinaryIO, nbytes: int, wbits: int,
                    max_input: int | None = None) -> tuple[np.ndarray, int, int]:
    """First `nbytes` inflated bytes (zlib/gzip, `wbits`) of the compressed stream `f`
    as a writable uint8 array (fewer where it ends), the inflated length counted up to
    ``nbytes + 1``, and the bytes of `f` the stream took up to its end (or as far as it
    was read): the compressed data (at most `max_input` bytes of them) are read a chunk
    at a time and no further than that, so a decompression bomb, or a file of more data
    than the header promises, costs no more memory than the samples promised and a
    chunk. Corrupt data raise ``zlib.error``."""
    buf = np.empty(nbytes, np.uint8)
    inflater = zlib.decompressobj(wbits)
    got, pending, left, taken = 0, b"", max_input, 0
    while got <= nbytes and not inflater.eof:
        if not pending:
            pending = f.read(INFLATE_CHUNK if left is None else min(INFLATE_CHUNK, left))
            if not pending:
                break
            left = None if left is None else left - len(pending)
            taken += len(pending)
        out = inflater.decompress(pending, min(nbytes + 1 - got, INFLATE_CHUNK))
        pending = inflater.unconsumed_tail
        kept = min(len(out), nbytes - got)
        buf[got:got + kept] = np.frombuffer(out, np.uint8, kept)
        got += len(out)
    used = taken - len(pending) - len(inflater.unused_data)
    return buf[:min(got, nbytes)], got, used
