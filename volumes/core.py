"""The `Volume` type and the error raised for bad volume input.

Conventions (DESIGN §2), stated once here and tested in ``tests/test_volumes_core.py``:

* ``data`` is indexed ``[z, y, x]`` (the on-disk order of raw files: x varies fastest) and
  holds the samples in their stored type when every value of that type is a float32
  exactly (`STORED_TYPES`: 8- and 16-bit integers, float32), else as float32 (saying
  what that rounds, refusing what it cannot hold: `_as_float32`); whatever
  reads it computes with float32 (or wider) values, so a volume's results do not depend
  on the type it is kept in.
* ``spacing`` and ``origin`` are given in (x, y, z) order, world units.
* The world position of voxel ``(k, j, i)`` (``data[k, j, i]``) is
  ``origin + (i, j, k) * spacing``.
* The volume's *world box* is the union of the voxel cells, ``origin - spacing/2`` to
  ``origin + (shape_xyz - 1/2) * spacing``; lattices span the same box, so texel centres
  of a scale-1 lattice coincide with the voxel samples.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from .errors import IsolumeError


class VolumeError(IsolumeError):
    """Bad volume input: the message names the file or value and what was expected."""


STORED_TYPES = (np.dtype(np.uint8), np.dtype(np.int8), np.dtype(np.uint16),
                np.dtype(np.int16), np.dtype(np.float32))
"""Sample types a `Volume` keeps as they are (a 512³ CT of bytes stays 128 MiB, not 512);
any other is converted to float32."""
HASH_CHUNK = 1 << 22
"""Samples converted to float32 at a time by `Volume.data_hash` and checked at a time by
`_as_float32`."""
FLOAT32_INTEGERS = 1 << 24
"""Every integer of magnitude up to 2²⁴ is a float32; beyond, some are not."""
FLOAT_ROUNDING_NOTED = 2.0**-16
"""Float samples rounded to float32 by more than this fraction of their range are
warned about: less is below a 16-bit sample's step and moves an isosurface by under
1/65536 of a voxel; float64 data in [0, 1] round by ~3e-8 of it."""
SPACING_RANGE = (1e-12, 1e12)
"""Voxel sizes accepted, world units: beyond them float32 world coordinates (GL, Embree,
mesh vertices) and their products underflow or overflow."""
WORLD_REACH = 1024.0
"""How far from the world origin a volume may lie, in multiples of its largest world
extent: float32 coordinates step by 2⁻²³ of their magnitude, so at 1024 extents out a
step is 1/8192 of the extent, a large part of a voxel of a volume thousands of voxels
across, and beyond it surfaces shred."""


@dataclass(frozen=True, eq=False)
class Volume:
    """A scalar field sampled on a rectilinear grid.

    Attributes:
        data: (Z, Y, X) samples: a type of `STORED_TYPES`.
        spacing: (3,) voxel size in x, y, z, world units (> 0).
        origin: (3,) world position of voxel (0, 0, 0), x, y, z.
        name: short human-readable name (file stem or synthetic spec).
        source: where the data came from (path or spec), for messages.
        suggested_iso: isovalues known to show the structure (synthetic volumes set
            them; `volumes.suggest_isovalues` derives them for loaded data).
        placement: how the samples were placed in the world (orientation applied, or
            why none was), for `isolume info`; "" when nothing was said.
    """

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "volume"
    source: str = ""
    suggested_iso: tuple[float, ...] = ()
    placement: str = ""
    _cache: dict[str, object] = field(default_factory=dict, init=False, repr=False,
                                      compare=False)  # a replaced volume starts afresh

    def __post_init__(self) -> None:
        where = self.source or self.name
        data = np.asarray(self.data)
        if data.ndim != 3:
            raise VolumeError(f"{where}: expected a 3-D array [z, y, x], got shape {data.shape}")
        if min(data.shape) < 2:
            raise VolumeError(
                f"{where}: volume of shape (z, y, x) = {data.shape} is smaller than 2×2×2; "
                "an isosurface needs at least two samples along every axis"
            )
        if not np.issubdtype(data.dtype, np.number) or np.iscomplexobj(data):
            raise VolumeError(f"{where}: expected real numbers, got dtype {data.dtype}")
        kept = data.dtype.newbyteorder("=")
        if kept in STORED_TYPES:
            data = np.ascontiguousarray(data, dtype=kept)
        else:
            data = _as_float32(data, where)
        finite = np.isfinite(data) if data.dtype.kind == "f" else np.ones(1, bool)
        if not finite.all():
            bad = int(data.size - np.count_nonzero(finite))
            if not finite.any():
                raise VolumeError(f"{where}: every value is NaN or Inf")
            raise VolumeError(
                f"{where}: {bad} NaN/Inf value(s) of {data.size}; isosurfaces through "
                "undefined values would be wrong, so they are refused — replace them "
                "(e.g. numpy.nan_to_num) before loading"
            )
        spacing, origin = checked_geometry(self.spacing, self.origin, where)
        _check_float32_reach(data.shape[::-1], spacing, origin, where)
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "origin", origin)

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Number of samples along x, y, z."""
        z, y, x = self.data.shape
        return (x, y, z)

    @property
    def value_range(self) -> tuple[float, float]:
        """(min, max) of the data."""
        if "range" not in self._cache:
            self._cache["range"] = (float(self.data.min()), float(self.data.max()))
        return self._cache["range"]

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """World box (lo, hi), each (3,) xyz: the union of the voxel cells."""
        sp = np.array(self.spacing)
        lo = np.array(self.origin) - 0.5 * sp
        return lo, lo + np.array(self.shape_xyz) * sp

    @property
    def sample_box(self) -> tuple[np.ndarray, np.ndarray]:
        """World box (lo, hi) spanned by the samples themselves, where isosurfaces live."""
        lo = np.array(self.origin)
        return lo, lo + (np.array(self.shape_xyz) - 1) * np.array(self.spacing)

    @property
    def diagonal(self) -> float:
        """Length of the sample box diagonal, world units."""
        lo, hi = self.sample_box
        return float(np.linalg.norm(hi - lo))

    def world_to_index(self, points_xyz: np.ndarray) -> np.ndarray:
        """(N, 3) world xyz -> (N, 3) fractional voxel indices in (z, y, x) order."""
        p = (np.asarray(points_xyz, np.float64) - self.origin) / self.spacing
        return p[:, ::-1]

    def index_to_world(self, index_zyx: np.ndarray) -> np.ndarray:
        """(N, 3) fractional voxel indices (z, y, x) -> (N, 3) world xyz."""
        return np.asarray(index_zyx, np.float64)[:, ::-1] * self.spacing + self.origin

    def data_hash(self) -> str:
        """SHA-256 of the samples as float32, shape and spacing, hex (identifies a volume,
        whatever type its samples are kept in)."""
        if "hash" not in self._cache:
            import hashlib

            h = hashlib.sha256()
            h.update(np.asarray(self.data.shape, np.int64).tobytes())
            h.update(np.asarray(self.spacing, np.float64).tobytes())
            flat = self.data.reshape(-1)
            for lo in range(0, flat.size, HASH_CHUNK):
                part = np.ascontiguousarray(flat[lo:lo + HASH_CHUNK], np.float32)
                h.update(memoryview(part).cast("B"))
            self._cache["hash"] = h.hexdigest()
        return self._cache["hash"]


def checked_geometry(spacing: npt.ArrayLike, origin: npt.ArrayLike, where: str
                     ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(spacing, origin) as float triples, x, y, z: spacing positive and within
    `SPACING_RANGE`, both finite.

    Raises:
        VolumeError: one line naming `where` and the bad value.
    """
    spacing = _triple(spacing, "spacing", where)
    if min(spacing) <= 0:
        raise VolumeError(f"{where}: spacing must be positive in x, y, z, got {spacing}")
    low, high = SPACING_RANGE
    if min(spacing) < low or max(spacing) > high:
        raise VolumeError(
            f"{where}: spacing {spacing} is outside {low:g} .. {high:g} world units, beyond "
            "what float32 world coordinates hold; rescale the units with --spacing X,Y,Z "
            "(e.g. millimetres for metres)")
    return spacing, _triple(origin, "origin", where)


def _check_float32_reach(shape_xyz: tuple[int, ...], spacing: tuple[float, float, float],
                        origin: tuple[float, float, float], where: str) -> None:
    """Refuse a volume (`shape_xyz` samples, `spacing` and `origin` x, y, z, world units)
    whose world box reaches farther from the world origin than `WORLD_REACH` times its
    largest extent: its float32 world coordinates would be too coarse for its voxels.

    Raises:
        VolumeError: one line naming `where`, how far the volume lies and what to do.
    """
    step = np.asarray(spacing)
    lo = np.asarray(origin) - 0.5 * step
    sizes = np.asarray(shape_xyz) * step
    farthest = float(np.abs(np.concatenate([lo, lo + sizes])).max())
    extent = float(sizes.max())
    if farthest <= WORLD_REACH * extent:
        return
    coarse = 2.0 ** (math.frexp(farthest)[1] - 24)  # float32's step at `farthest`
    raise VolumeError(
        f"{where}: the volume lies {farthest:.6g} world units from the world origin, "
        f"{farthest / extent:.3g} times its largest extent {extent:.6g} (at most "
        f"{WORLD_REACH:g}): float32 world coordinates step by {coarse:.3g} there "
        f"({coarse / step.min():.3g} × the voxel size); give the volume an origin near it: "
        "--origin 0,0,0 (origin= in Python)")


def _as_float32(data: np.ndarray, where: str) -> np.ndarray:
    """(Z, Y, X) float32 copy of samples of a type not in `STORED_TYPES`.

    Integers beyond ±2²⁴ that float32 does not hold exactly, and floats rounded by more
    than `FLOAT_ROUNDING_NOTED` of their range, are said once on stderr
    (``isolume: warning: …``, with what was lost); exact conversions say nothing.

    Raises:
        VolumeError: a finite value beyond float32's range.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.ascontiguousarray(data, dtype=np.float32)
    if data.dtype.kind in "iu":
        lost = _integer_rounding(data, out, where)
    else:
        lost = _float_rounding(data, out, where)
    if lost:
        print(f"isolume: warning: {lost}", file=sys.stderr)
    return out


def _slabs(data: np.ndarray, out: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Flat (values, their float32) of the (Z, Y, X) `data` and `out`, a few z planes at
    a time (about `HASH_CHUNK` samples, one plane where that is more): a copy of a
    slab at most where `data` is not contiguous."""
    rows = max(1, HASH_CHUNK // max(1, data[0].size))
    for k in range(0, data.shape[0], rows):
        yield data[k:k + rows].reshape(-1), out[k:k + rows].reshape(-1)


def _integer_rounding(data: np.ndarray, out: np.ndarray, where: str) -> str:
    """What rounding the integer `data` to float32 (`out`) lost, or "" where every value
    is exact."""
    lo, hi = int(data.min()), int(data.max())
    if -FLOAT32_INTEGERS <= lo and hi <= FLOAT32_INTEGERS:
        return ""
    in_float64 = -(1 << 53) <= lo and hi <= 1 << 53  # the difference is exact there
    count, largest, example = 0, 0, (0, 0.0)
    for values, rounded in _slabs(data, out):
        if in_float64:
            change = np.abs(np.subtract(values, rounded, dtype=np.float64))
        else:
            change = _integer_change(values, rounded)
        count += int(np.count_nonzero(change))
        if int(change.max()) > largest:
            at = int(np.argmax(change))
            largest, example = int(change.max()), (int(values[at]), float(rounded[at]))
    if not count:
        return ""
    return (f"{where}: {data.dtype} samples are kept as float32, the type isolume computes "
            f"with, which holds integers beyond ±{FLOAT32_INTEGERS} (2^24) only in steps: "
            f"{count:,} of {data.size:,} values were rounded, by up to {largest} (e.g. "
            f"{example[0]} became {int(example[1])}); neighbouring values may have merged")


def _integer_change(values: np.ndarray, rounded: np.ndarray) -> np.ndarray:
    """(N,) uint64 |value - its float32| of (N,) integers and their (N,) float32 roundings,
    exact (in integers: float64 does not hold every 64-bit integer)."""
    magnitude = values.astype(np.uint64)
    negative = values < 0
    magnitude[negative] = ~magnitude[negative] + np.uint64(1)  # two's complement
    kept = np.abs(rounded.astype(np.float64))
    top = kept >= 2.0**64  # the float32 2^64, above every uint64
    kept_int = np.where(top, 0.0, kept).astype(np.uint64)
    change = np.where(magnitude > kept_int, magnitude - kept_int, kept_int - magnitude)
    return np.where(top, ~magnitude + np.uint64(1), change)  # 2^64 - magnitude


def _float_rounding(data: np.ndarray, out: np.ndarray, where: str) -> str:
    """What rounding the float `data` to float32 (`out`) lost, or "" where it moved no
    value by more than `FLOAT_ROUNDING_NOTED` of their range.

    Raises:
        VolumeError: a finite value became infinite (beyond float32's range).
    """
    lo, hi, largest, example = np.inf, -np.inf, 0.0, (0.0, 0.0)
    for values, rounded in _slabs(data, out):
        if np.isinf(rounded).any():
            _check_float32_range(values, rounded, where)
        # a slab's NaN (refused after) makes its range and change NaN: left out of both
        lo, hi = min(lo, float(values.min())), max(hi, float(values.max()))
        change = np.abs(np.subtract(values, rounded, dtype=np.float64))
        if change.max() > largest:
            at = int(np.argmax(change))
            largest, example = float(change[at]), (float(values[at]), float(rounded[at]))
    span = hi - lo
    if not (span > 0 and largest > FLOAT_ROUNDING_NOTED * span):
        return ""
    return (f"{where}: {data.dtype} samples are kept as float32, the type isolume computes "
            f"with: values were rounded by up to {largest:.3g}, {largest / span:.2g} of their "
            f"range {lo:.9g} .. {hi:.9g} (e.g. {example[0]!r} became {example[1]!r}); "
            "neighbouring values may have merged")


def _check_float32_range(values: np.ndarray, rounded: np.ndarray, where: str) -> None:
    """Refuse a finite value of (N,) `values` whose float32 (of (N,) `rounded`) is
    infinite: beyond float32's range."""
    beyond = np.flatnonzero(np.isfinite(values) & np.isinf(rounded))
    if beyond.size:
        raise VolumeError(
            f"{where}: value {float(values[beyond[0]]):.6g} ({values.dtype}) is beyond "
            f"float32's range (±{np.finfo(np.float32).max:.6g}), the type isolume computes "
            "with; rescale the samples")


def _triple(value, what: str, where: str) -> tuple[float, float, float]:
    """Validate a 3-vector of finite floats."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise VolumeError(
            f"{where}: {what} must be three numbers (x, y, z), got {value!r}"
        ) from None
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise VolumeError(f"{where}: {what} must be three finite numbers (x, y, z), got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))
