"""Zarr volumes (``.zarr`` folders, Zarr formats 2 and 3) via the zarr library (extra
``zarr``): a 3-D array, or an OME-Zarr multiscale image (NGFF 0.1 to 0.5). Nothing but
metadata is read here: the loader returns a `ZarrVolume`, which reads only the chunks
under the slices asked of it.

* A plain array holds samples ``[z, y, x]`` (leading axes of length 1 are dropped); it
  carries no spacing or origin (``--spacing`` gives one).
* An OME-Zarr image is the first entry of ``multiscales`` (in ``.zattrs``, or under
  ``"ome"`` in ``zarr.json``). `level` picks one of its ``datasets`` (0, the default, is
  the full resolution). Its ``axes`` name the space axes x, y, z (in any order); of every
  other axis (time, channel) the first index is taken. Each dataset's
  ``coordinateTransformations`` (scale, translation), followed by the image's, give the
  spacing and origin along x, y, z, in the axes' units.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import READ_ERRORS, Loaded, one_line, optional_module

ZARR_MARKERS = (".zarray", ".zgroup", "zarr.json")
"""Metadata files of which a Zarr folder holds one at its top."""

_SPACE = ("z", "y", "x")


class ZarrVolume:
    """The (Z, Y, X) samples of a Zarr array, read lazily.

    Attributes:
        array: the zarr array (any number of axes).
        space: positions in `array` of its z, y and x axes; every other axis is read at
            index 0.
        shape: (Z, Y, X) sample counts.
        dtype: the samples' numpy type.
        where: the folder, for messages.
    """

    def __init__(self, array: Any, space: tuple[int, int, int], where: str) -> None:
        self.array = array
        self.space = space
        self.where = where
        self.shape: tuple[int, ...] = tuple(int(array.shape[axis]) for axis in space)
        self.dtype: np.dtype[Any] = np.dtype(array.dtype)

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray:
        """Samples ``[z0:z1, y0:y1, x0:x1]`` (three slices), read from the chunks they
        touch; an array of those shapes in z, y, x order.

        Raises:
            VolumeError: a chunk that cannot be read or decoded (one line).
        """
        full: list[Any] = [0] * len(self.array.shape)
        for axis, part in zip(self.space, key, strict=True):
            full[axis] = part
        try:
            block = np.asarray(self.array[tuple(full)])
        except (RuntimeError, *READ_ERRORS) as exc:  # codecs raise RuntimeError
            ranges = ", ".join(f"{s.start}:{s.stop}" for s in key)
            raise VolumeError(f"{self.where}: cannot read the Zarr chunks of samples "
                              f"[z, y, x] = [{ranges}]: {one_line(exc)}") from None
        kept = sorted(self.space)  # the sliced axes in the array's order
        return block.transpose([kept.index(axis) for axis in self.space])


def looks_like_zarr(path: Path) -> bool:
    """True for a folder named ``*.zarr`` or one holding Zarr metadata at its top."""
    return path.suffix.lower() == ".zarr" or any((path / m).is_file() for m in ZARR_MARKERS)


def load_zarr(path: Path, level: int | None) -> tuple[Loaded, str]:
    """A Zarr folder → (`ZarrVolume`, spacing xyz or None, origin xyz or None, None) and
    a line for `isolume info` saying which array, level and indices were taken.

    Args:
        path: the ``.zarr`` folder.
        level: multiscale level of an OME-Zarr image (None: 0, the full resolution).

    Raises:
        VolumeError: not a Zarr folder, a group that is no OME-Zarr image, a level it
            lacks, fewer than three space axes (the samples' type is checked by the
            caller, `volumes.region.check_sample_type`).
    """
    zarr = optional_module("zarr", path)
    where = str(path)
    if not path.is_dir():
        raise VolumeError(f"{where}: a Zarr store must be a folder; this is a file")
    try:
        node = zarr.open(str(path), mode="r")
    except FileNotFoundError:
        raise VolumeError(f"{where}: not a Zarr folder: it holds none of "
                          f"{', '.join(ZARR_MARKERS)}") from None
    if isinstance(node, zarr.Array):
        if level not in (None, 0):
            raise VolumeError(f"{where}: --level {level}: a plain Zarr array has one level "
                              "(0); levels come with OME-Zarr multiscale images")
        volume = ZarrVolume(node, _plain_space(node.shape, where), where)
        return (volume, None, None, None), "Zarr array"
    image = _first_image(dict(node.attrs), node, where)
    return _load_image(node, image, level, zarr.Array, where)


def _plain_space(shape: tuple[int, ...], where: str) -> tuple[int, int, int]:
    """Positions of z, y, x in a plain array: its last three axes, after leading axes of
    length 1."""
    lead = shape[:-3]
    if len(shape) < 3 or any(n != 1 for n in lead):
        raise VolumeError(f"{where}: expected a 3-D Zarr array [z, y, x], got shape "
                          f"{tuple(shape)}; more axes need OME-Zarr metadata naming them")
    n = len(shape)
    return (n - 3, n - 2, n - 1)


def _first_image(attrs: dict, group: Any, where: str) -> dict:
    """The first entry of the group's OME-Zarr ``multiscales``."""
    ome = attrs.get("ome")
    images = attrs.get("multiscales") or (ome.get("multiscales") if isinstance(ome, dict)
                                          else None)
    if isinstance(images, list) and images and isinstance(images[0], dict):
        return images[0]
    names = sorted([*group.array_keys(), *group.group_keys()])
    shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
    hint = f"; pass one of them as {where}/NAME" if names else ""
    raise VolumeError(f"{where}: a Zarr group without OME-Zarr multiscales metadata "
                      f"(holding {shown or 'nothing'}); expected a 3-D array or an OME-Zarr "
                      f"image{hint}")


def _load_image(group: Any, image: dict, level: int | None, array_type: type,
                where: str) -> tuple[Loaded, str]:
    """The `level` of an OME-Zarr `image` (a ``multiscales`` entry) in `group`, whose
    datasets must be arrays (instances of `array_type`: zarr's ``Array``)."""
    datasets = image.get("datasets")
    if not isinstance(datasets, list) or not datasets:
        raise VolumeError(f"{where}: OME-Zarr multiscales lists no datasets")
    k = 0 if level is None else level
    if not 0 <= k < len(datasets):
        raise VolumeError(f"{where}: --level {level}: this OME-Zarr image has "
                          f"{len(datasets)} level(s), 0 to {len(datasets) - 1}")
    arrays = [_dataset_array(group, d, i, array_type, where)
              for i, d in enumerate(datasets)]
    array = arrays[k]
    axes = _axes(image, len(array.shape), where)
    space = _space_axes(axes, where)
    volume = ZarrVolume(array, space, where)
    scale, translation = _world_transform(
        [*_transforms(datasets[k], where), *_transforms(image, where)], len(axes), where)
    spacing = tuple(float(scale[space[a]]) for a in (2, 1, 0))
    origin = tuple(float(translation[space[a]]) for a in (2, 1, 0))
    return (volume, spacing, origin, None), _describe(k, arrays, axes, space)


def _dataset_array(group: Any, dataset: Any, index: int, array_type: type,
                   where: str) -> Any:
    """The zarr array of one ``datasets`` entry (its metadata only): the node its path
    names in `group`, which must be an `array_type`."""
    name = dataset.get("path") if isinstance(dataset, dict) else None
    try:
        node = group[str(name)]
    except (KeyError, FileNotFoundError):
        raise VolumeError(f"{where}: OME-Zarr level {index}: dataset path {name!r} not "
                          "found in the group") from None
    if not isinstance(node, array_type):
        raise VolumeError(f"{where}: OME-Zarr level {index}: dataset path {name!r} names a "
                          f"{type(node).__name__.lower()}, not an array; expected the path "
                          "of the level's array")
    return node


def _axes(image: dict, ndim: int, where: str) -> list[dict]:
    """[{name, type, unit}] of the image's axes (NGFF 0.4+: dicts; 0.3: names; older:
    the last `ndim` of t, c, z, y, x)."""
    raw = image.get("axes")
    if raw is None:
        raw = list("tczyx"[-ndim:]) if ndim <= 5 else []
    axes = [a if isinstance(a, dict) else {"name": str(a)} for a in raw]
    if len(axes) != ndim:
        raise VolumeError(f"{where}: OME-Zarr axes {[a.get('name') for a in axes]} do not "
                          f"match the {ndim} axes of the array")
    return axes


def _space_axes(axes: list[dict], where: str) -> tuple[int, int, int]:
    """Positions of the axes named z, y, x."""
    names = [str(a.get("name", "")).lower() for a in axes]
    if not all(n in names for n in _SPACE):
        raise VolumeError(f"{where}: OME-Zarr axes {', '.join(names)}: expected space axes "
                          "z, y and x (a 3-D image)")
    z, y, x = (names.index(n) for n in _SPACE)
    return (z, y, x)


def _transforms(entry: dict, where: str) -> list[dict]:
    """The ``coordinateTransformations`` list of a dataset or an image ([] if none)."""
    transforms = entry.get("coordinateTransformations", [])
    if not isinstance(transforms, list) or not all(isinstance(t, dict) for t in transforms):
        raise VolumeError(f"{where}: OME-Zarr coordinateTransformations must be a list of "
                          f"objects, got {transforms!r}")
    return transforms


def _world_transform(transforms: list[dict], ndim: int,
                     where: str) -> tuple[np.ndarray, np.ndarray]:
    """(scale, translation), each (ndim,), of `transforms` applied in order: the world
    position of index i is ``i * scale + translation``."""
    scale, translation = np.ones(ndim), np.zeros(ndim)
    for t in transforms:
        kind = t.get("type")
        if kind == "identity":
            continue
        if kind not in ("scale", "translation") or kind not in t:
            raise VolumeError(f"{where}: OME-Zarr coordinate transformation {t!r}: expected "
                              "a scale or translation given as a list of numbers")
        try:
            vector = np.asarray(t[kind], np.float64).reshape(-1)
        except (TypeError, ValueError):
            vector = np.zeros(0)
        if vector.shape != (ndim,) or not np.isfinite(vector).all():
            raise VolumeError(f"{where}: OME-Zarr {kind} {t[kind]!r}: expected {ndim} "
                              "finite numbers, one per axis")
        if kind == "scale":
            scale, translation = scale * vector, translation * vector
        else:
            translation = translation + vector
    return scale, translation


def _describe(level: int, arrays: list, axes: list[dict], space: tuple[int, int, int]) -> str:
    """``OME-Zarr level K of N (…dims of every level…)``, the indices taken on other
    axes, and the units of the space axes."""
    dims = ", ".join(
        f"{i}: {' x '.join(str(a.shape[space[j]]) for j in (2, 1, 0))}"
        for i, a in enumerate(arrays))
    text = f"OME-Zarr level {level} of {len(arrays)} (dims X x Y x Z per level: {dims})"
    others = [f"{a.get('name')} 0 of {arrays[level].shape[i]}"
              for i, a in enumerate(axes) if i not in space]
    if others:
        text += f"; first index taken along the other axes: {', '.join(others)}"
    units = sorted({str(axes[i]["unit"]) for i in space if axes[i].get("unit")})
    if units:
        text += f"; world units {', '.join(units)}"
    return text
