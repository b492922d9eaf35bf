"""Parts of volumes: ``--crop`` voxel ranges and ``--downsample`` block means.

`read_region` reads a part slab by slab (a few z planes at a time) from any array that
slices lazily — a numpy memmap of a raw file, a ``.npy`` opened with ``mmap_mode``, a Zarr
array — so memory holds the result and one slab, not the whole volume. `crop_downsample`
applies the same to a `Volume` in memory.

World coordinates are kept (conventions in :mod:`volumes.core`):

* a crop from voxel (i0, j0, k0) on has its origin at that voxel's world position,
  ``origin + (i0, j0, k0) * spacing``; the spacing is unchanged;
* downsampling by N replaces each block of N×N×N voxels by its mean, placed at the
  block's centre: spacing × N, origin at the first block's centre, ``origin + (N − 1)/2 *
  spacing`` — so an isosurface stays where it was in world space, within a block.

Along an axis whose range of L voxels is not a multiple of N, the last ``L mod N`` voxels
(fewer than one block) are left out: every sample is the mean of a whole block and sits at
its centre, and the result spans at most N − 1 voxels less than the range at the far end.
`Region.describe` says so where it happens.
"""

from __future__ import annotations

import operator
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from isolume.volumes.core import STORED_TYPES, Volume, VolumeError

CROP_SYNTAX = ("X0:X1,Y0:Y1,Z0:Z1 (voxel index ranges along x, y, z from 0, end exclusive; "
               "':' for a whole axis, '100:' from voxel 100 on, ':50' up to voxel 50)")
"""What ``--crop`` accepts, for messages and ``--help``."""

SLAB_BYTES = 16 << 20
"""Bytes of source samples read at once (at least the z planes of one output plane)."""

_RANGE = re.compile(r"^\s*(\d*)\s*:\s*(\d*)\s*$")


@dataclass(frozen=True)
class Crop:
    """Voxel index ranges as given, not yet checked against a volume.

    Attributes:
        ranges: ((start, stop),) × 3 along x, y, z, stop exclusive; None for "from the
            first voxel" / "to the last".
        text: the ``X0:X1,Y0:Y1,Z0:Z1`` text, for messages.
    """

    ranges: tuple[tuple[int | None, int | None], ...]
    text: str


@dataclass(frozen=True)
class Region:
    """A part of a volume of `dims` voxels: voxels `start` to `stop` (x, y, z, stop
    exclusive) in blocks of `factor`³ voxels.

    Attributes:
        dims: (3,) voxel counts of the whole volume, x, y, z.
        start, stop: (3,) voxel index range along x, y, z.
        factor: block edge N in voxels (1: no downsampling).
    """

    dims: tuple[int, int, int]
    start: tuple[int, int, int]
    stop: tuple[int, int, int]
    factor: int = 1

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Samples of the result along x, y, z: whole blocks in each range."""
        x, y, z = ((b - a) // self.factor for a, b in zip(self.start, self.stop, strict=True))
        return (x, y, z)

    @property
    def left_out(self) -> tuple[int, int, int]:
        """Voxels at the far end of each range (x, y, z) that fill no whole block."""
        x, y, z = ((b - a) % self.factor for a, b in zip(self.start, self.stop, strict=True))
        return (x, y, z)

    @property
    def whole(self) -> bool:
        """True for the whole volume at full resolution (nothing to do)."""
        return self.start == (0, 0, 0) and self.stop == self.dims and self.factor == 1

    @property
    def nbytes(self) -> int:
        """Bytes of the result at most (float32 samples)."""
        return 4 * int(np.prod(self.shape_xyz, dtype=np.int64))

    def spacing(self, spacing: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
        """(3,) voxel size of the result, x, y, z: `spacing` × factor."""
        x, y, z = (float(s) * self.factor for s in spacing)
        return (x, y, z)

    def origin(self, spacing: npt.ArrayLike, origin: npt.ArrayLike) -> tuple[float, float, float]:
        """(3,) world position x, y, z of the result's first sample: the centre of its
        first block, ``origin + (start + (factor − 1)/2) * spacing``."""
        first = np.asarray(self.start, np.float64) + (self.factor - 1) / 2
        x, y, z = np.asarray(origin, np.float64) + first * np.asarray(spacing, np.float64)
        return (float(x), float(y), float(z))

    def describe(self) -> str:
        """One line for `isolume info`: the voxels kept and the blocks averaged."""
        parts = []
        if self.start != (0, 0, 0) or self.stop != self.dims:
            ranges = ", ".join(f"{axis} {a}:{b}" for axis, a, b in
                               zip("xyz", self.start, self.stop, strict=True))
            parts.append(f"cropped to voxels {ranges} of {_dims_text(self.dims)}")
        if self.factor > 1:
            f = self.factor
            text = f"downsampled by {f}: means of {f}×{f}×{f}-voxel blocks"
            dropped = [f"{n} along {axis}" for axis, n in zip("xyz", self.left_out, strict=True)
                       if n]
            if dropped:
                text += f" (the last {', '.join(dropped)} left out: no whole block)"
            parts.append(text)
        return "; ".join(parts)


def parse_crop(text: str) -> Crop:
    """``X0:X1,Y0:Y1,Z0:Z1`` → `Crop` (syntax only; `resolve_region` checks the ranges
    against a volume).

    Raises:
        VolumeError: not three ranges of non-negative integers (see `CROP_SYNTAX`).
    """
    parts = str(text).split(",")
    matches = [_RANGE.match(part) for part in parts]
    if len(parts) != 3 or not all(matches):
        raise VolumeError(f"--crop {text!r}: expected {CROP_SYNTAX}")
    ranges = tuple((int(m[1]) if m[1] else None, int(m[2]) if m[2] else None)
                   for m in matches if m is not None)
    return Crop(ranges, str(text))


def check_factor(factor: Any) -> int:
    """The downsampling factor as an int ≥ 1.

    Raises:
        VolumeError: not an integer, or below 1.
    """
    try:
        value = operator.index(factor)
    except TypeError:
        raise VolumeError(f"--downsample {factor!r}: expected an integer factor ≥ 1") from None
    if value < 1 or isinstance(factor, bool):
        raise VolumeError(f"--downsample {factor!r}: expected an integer factor ≥ 1")
    return value


def resolve_region(dims_xyz: Sequence[int] | np.ndarray, crop: Crop | str | None, factor: int,
                   where: str) -> Region:
    """The `Region` of `crop` (None: the whole volume) and `factor` in a volume of
    `dims_xyz` voxels.

    Raises:
        VolumeError: one line naming `where`, the range and the volume's dims: a range
            past the volume, empty, shorter than 2 voxels, or fewer than 2 blocks.
    """
    dims = (int(dims_xyz[0]), int(dims_xyz[1]), int(dims_xyz[2]))
    factor = check_factor(factor)
    crop = parse_crop(crop) if isinstance(crop, str) else crop
    ranges = crop.ranges if crop is not None else ((None, None),) * 3
    start, stop = [], []
    for axis, n, (a, b) in zip("xyz", dims, ranges, strict=True):
        a, b = 0 if a is None else a, n if b is None else b
        _check_range(axis, a, b, n, factor, crop, dims, where)
        start.append(a)
        stop.append(b)
    return Region(dims, (start[0], start[1], start[2]), (stop[0], stop[1], stop[2]), factor)


def _check_range(axis: str, a: int, b: int, n: int, factor: int, crop: Crop | None,
                 dims: tuple[int, int, int], where: str) -> None:
    """Refuse a range a:b along `axis` (n voxels) that the volume cannot give."""
    what = f"--crop {crop.text!r}: {axis} range {a}:{b}" if crop is not None else None
    of = f"(volume dims {_dims_text(dims)})"
    if what and (a >= n or b > n):
        raise VolumeError(f"{where}: {what} goes past the {n} voxels along {axis} {of}")
    if what and b <= a:
        raise VolumeError(f"{where}: {what} is empty {of}")
    if what and b - a < 2:
        raise VolumeError(f"{where}: {what} holds 1 voxel; an isosurface needs at least 2 "
                          f"along every axis {of}")
    if factor > 1 and (b - a) // factor < 2:
        span = f"the {b - a} voxels of {axis} range {a}:{b}" if what else (
            f"the {n} voxels along {axis}")
        raise VolumeError(f"{where}: --downsample {factor} leaves {(b - a) // factor} "
                          f"block(s) of {span}; at least 2 are needed {of}")


def check_sample_type(dtype: npt.DTypeLike, where: str) -> None:
    """Refuse samples that are not integers, floats or booleans (before any is read).

    Raises:
        VolumeError: one line naming `where` and the type.
    """
    if np.dtype(dtype).kind not in "biuf":
        raise VolumeError(f"{where}: samples of type {dtype} are not supported; expected "
                          "integers, floats or booleans")


def read_region(array: Any, region: Region) -> np.ndarray:
    """The samples of `region`, read slab by slab.

    Args:
        array: (Z, Y, X) samples of numeric or bool type: anything that takes basic
            slices ``array[z0:z1, y0:y1, x0:x1]`` and has ``shape`` and ``dtype``
            (ndarray, numpy memmap, a Zarr volume), read only where the region lies.
        region: the part to read, in `array`'s voxels.

    Returns:
        (Z', Y', X'), with (X', Y', Z') = ``region.shape_xyz``: float32 block means of
        ``factor``³ voxels, or for factor 1 the samples themselves (in their own type
        where `Volume` keeps it: `STORED_TYPES`, else float32). Memory: the result,
        plus at most `SLAB_BYTES` of source samples (or the z planes of one output plane
        where those are more) and their float64 means.
    """
    f = region.factor
    nx, ny, nz = region.shape_xyz
    x0, y0, z0 = region.start
    ys, xs = slice(y0, y0 + ny * f), slice(x0, x0 + nx * f)
    plane_bytes = f * (ny * f) * (nx * f) * np.dtype(array.dtype).itemsize
    rows = max(1, SLAB_BYTES // plane_bytes)
    kept = np.dtype(array.dtype).newbyteorder("=")
    out = np.empty((nz, ny, nx), kept if f == 1 and kept in STORED_TYPES else np.float32)
    for k0 in range(0, nz, rows):
        k1 = min(nz, k0 + rows)
        slab = np.asarray(array[z0 + k0 * f: z0 + k1 * f, ys, xs])
        out[k0:k1] = block_means(slab, f)
    return out


def block_means(samples: np.ndarray, factor: int) -> np.ndarray:
    """(Z, Y, X) samples, each a multiple of `factor` → (Z/f, Y/f, X/f) means of f³-voxel
    blocks (float64; `samples` itself for factor 1). A strided view (a slice of a memmap)
    is averaged in place, without a copy."""
    if factor == 1:
        return samples
    z, y, x = (n // factor for n in samples.shape)
    blocks = samples.reshape(z, factor, y, factor, x, factor)
    return blocks.mean(axis=(1, 3, 5), dtype=np.float64)


def crop_downsample(volume: Volume, crop: Crop | str | None = None,
                    downsample: int = 1) -> Volume:
    """`volume` cropped to voxel ranges `crop` (``X0:X1,Y0:Y1,Z0:Z1``) and downsampled
    by block means of `downsample`³ voxels, in the same world place (module docstring).

    Args:
        volume: (Z, Y, X) samples in memory.
        crop: voxel index ranges along x, y, z (`parse_crop`), or None for all.
        downsample: block edge N ≥ 1 in voxels.

    Returns:
        The part as a new `Volume` (spacing × N, origin at the first block's centre; its
        ``placement`` says what was kept), or `volume` itself when the part is the whole.

    Raises:
        VolumeError: bad crop text, a range the volume does not hold, a bad factor.
    """
    where = volume.source or volume.name
    region = resolve_region(volume.shape_xyz, crop, downsample, where)
    if region.whole:
        return volume
    return Volume(read_region(volume.data, region), spacing=region.spacing(volume.spacing),
                  origin=region.origin(volume.spacing, volume.origin), name=volume.name,
                  source=volume.source, suggested_iso=volume.suggested_iso,
                  placement=join_placement(volume.placement, region.describe()))


def join_placement(placement: str, more: str) -> str:
    """``placement; more`` (either alone where the other is empty)."""
    return "; ".join(p for p in (placement, more) if p)


def _dims_text(dims) -> str:
    """``X x Y x Z``."""
    return " x ".join(str(int(n)) for n in dims)
