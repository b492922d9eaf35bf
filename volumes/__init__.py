"""Volumes: loading, synthetic fields, sampling and isosurfaces. No GL, no ray tracing.

Public API::

    volumes.load(spec) -> Volume          # file path or "synthetic:NAME[:SIZE]"
    volumes.load(spec, crop="0:128,:,64:", downsample=2)   # a part, in the same world place
    volumes.crop_downsample(volume, crop, downsample) -> Volume   # the same, in memory
    volumes.isosurface(volume, iso) -> Mesh
    volumes.level_points(volume, iso) -> (N, 3)   # points of that surface (for framing)
    volumes.suggest_isovalues(volume) -> tuple[float, ...]
    volumes.turn_up(volume, "-z") -> Volume   # the volume's -z axis pointing up
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any

from isolume.volumes.core import STORED_TYPES, Volume, VolumeError
from isolume.volumes.orientation import UP_AXES, turn_up
from isolume.volumes.region import CROP_SYNTAX, crop_downsample
from isolume.volumes.stats import histogram_lines, suggest_isovalues
from isolume.volumes.synthetic import DEFAULT

if TYPE_CHECKING:
    from isolume.volumes.cubes import marching_cubes, tracing_surface
    from isolume.volumes.field import (
        gradient_at,
        newton_to_level,
        normals_at,
        value_at,
        values_along_normals,
        values_on_grid,
    )
    from isolume.volumes.mesh import (
        Mesh,
        check_isovalue,
        isosurface,
        level_points,
    )

_COMPILED = {
    "tracing_surface": "cubes", "gradient_at": "field", "newton_to_level": "field",
    "normals_at": "field", "value_at": "field",
    "values_along_normals": "field", "values_on_grid": "field", "Mesh": "mesh",
    "check_isovalue": "mesh", "isosurface": "mesh", "level_points": "mesh",
    "marching_cubes": "cubes",
}
"""Names whose modules compile kernels (numba): imported when first used (PEP 562), so
that ``import isolume.volumes`` (and the Python API's ``import isolume``) stays light."""


def __getattr__(name: str) -> object:
    if name not in _COMPILED:
        raise AttributeError(f"module 'isolume.volumes' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"isolume.volumes.{_COMPILED[name]}"), name)
    globals()[name] = value
    return value


__all__ = [
    "CROP_SYNTAX",
    "DEFAULT",
    "STORED_TYPES",
    "UP_AXES",
    "Mesh",
    "Volume",
    "VolumeError",
    "check_isovalue",
    "crop_downsample",
    "gradient_at",
    "histogram_lines",
    "isosurface",
    "level_points",
    "load",
    "marching_cubes",
    "newton_to_level",
    "normals_at",
    "suggest_isovalues",
    "tracing_surface",
    "turn_up",
    "value_at",
    "values_along_normals",
    "values_on_grid",
]


def load(spec: str | os.PathLike[str] | None = None, *, crop: str | None = None,
         downsample: int = 1, **options: Any) -> Volume:
    """Load a volume from a file path or build ``synthetic:NAME[:SIZE]``, or a part of it.

    Args:
        spec: path or synthetic spec; None gives the built-in default (`DEFAULT`).
        crop: ``X0:X1,Y0:Y1,Z0:Z1`` voxel index ranges along x, y, z (end exclusive,
            see `CROP_SYNTAX`); None for the whole volume.
        downsample: N ≥ 1: means of N³-voxel blocks, spacing × N (`volumes.region`).
        **options: ``spacing``, ``origin`` ((3,) x, y, z, world units: they override the
            file's or the synthetic volume's own); for files, also ``dims``, ``dtype``,
            ``level`` (see `volumes.io.load_file`).

    Files read lazily where their format allows (raw, NRRD raw, ``.npy``, Zarr): only the
    part is read. A synthetic volume is built whole, placed, then cut.
    """
    spec = DEFAULT if spec is None else spec
    if isinstance(spec, str) and spec.startswith("synthetic:"):
        return crop_downsample(_synthetic(spec, **options), crop, downsample)
    from isolume.volumes.io import load_file

    return load_file(spec, crop=crop, downsample=downsample, **options)


FILE_OPTIONS = {"dims": ("--dims", "a raw file's size"),
                "dtype": ("--dtype", "a raw file's sample type"),
                "level": ("--level", "the level of an OME-Zarr multiscale image")}
"""`load`'s options that describe a file: the command-line option that gives each, and
what it gives."""


def _synthetic(spec: str, spacing: Any = None, origin: Any = None, **given: Any) -> Volume:
    """The synthetic volume `spec` (``synthetic:NAME[:SIZE]``) at the `spacing` and
    `origin` asked ((3,) x, y, z, world units; None: its own).

    Raises:
        VolumeError: for an option of `FILE_OPTIONS` given: a generated volume has no file
            for it to describe.
        TypeError: for an option `load` does not know, as `volumes.io.load_file` does.
    """
    from isolume.volumes.synthetic import parse

    for name, value in given.items():
        if name not in FILE_OPTIONS:
            raise TypeError(f"load() got an unexpected keyword argument {name!r}")
        if value is not None:
            option, what = FILE_OPTIONS[name]
            text = ",".join(map(str, value)) if isinstance(value, tuple) else value
            raise VolumeError(f"{spec}: {option} {text} gives {what}; a synthetic volume is "
                              "generated (its size: synthetic:NAME:SIZE)")
    volume = parse(spec)
    if spacing is None and origin is None:
        return volume
    return dataclasses.replace(volume, spacing=volume.spacing if spacing is None else spacing,
                               origin=volume.origin if origin is None else origin)
