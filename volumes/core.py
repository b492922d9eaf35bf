"""The `Volume` type and the error raised for bad volume input.

Conventions (DESIGN §2), stated once here and tested in ``tests/test_volumes_core.py``:

* ``data`` is indexed ``[z, y, x]`` (the on-disk order of raw files: x varies fastest) and
  holds the samples in their stored type when every value of that type is a float32
  exactly (`STORED_TYPES`: 8- and 16-bit integers, float32), else as float32; whatever
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
"""Samples converted to float32 at a time by `Volume.data_hash`."""


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
    _cache: dict[str, object] = field(default_factory=dict, repr=False, compare=False)

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
        data = np.ascontiguousarray(data, dtype=kept if kept in STORED_TYPES else np.float32)
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
    """(spacing, origin) as float triples, x, y, z: spacing positive, both finite.

    Raises:
        VolumeError: one line naming `where` and the bad value.
    """
    spacing = _triple(spacing, "spacing", where)
    if min(spacing) <= 0:
        raise VolumeError(f"{where}: spacing must be positive in x, y, z, got {spacing}")
    return spacing, _triple(origin, "origin", where)


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
