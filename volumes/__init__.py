"""Volumes: loading, synthetic fields, sampling and isosurfaces. No GL, no ray tracing.

Public API::

    volumes.load(spec) -> Volume          # file path or "synthetic:NAME[:SIZE]"
    volumes.isosurface(volume, iso) -> Mesh
    volumes.suggest_isovalues(volume) -> tuple[float, ...]
    volumes.turn_up(volume, "-z") -> Volume   # the volume's -z axis pointing up
"""

from __future__ import annotations

import os

from isolume.volumes.core import Volume, VolumeError
from isolume.volumes.cubes import tracing_surface
from isolume.volumes.field import (
    gradient_at,
    gradient_grid,
    newton_to_level,
    normals_at,
    value_at,
    values_along_normals,
    values_on_grid,
)
from isolume.volumes.mesh import Mesh, check_isovalue, isosurface, marching_cubes
from isolume.volumes.orientation import UP_AXES, turn_up
from isolume.volumes.stats import histogram_lines, suggest_isovalues
from isolume.volumes.synthetic import DEFAULT

__all__ = [
    "DEFAULT",
    "UP_AXES",
    "Mesh",
    "Volume",
    "VolumeError",
    "check_isovalue",
    "gradient_at",
    "gradient_grid",
    "histogram_lines",
    "isosurface",
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


def load(spec: str | os.PathLike | None = None, **options) -> Volume:
    """Load a volume from a file path or build ``synthetic:NAME[:SIZE]``.

    Args:
        spec: path or synthetic spec; None gives the built-in default (`DEFAULT`).
        **options: for files, ``dims``, ``dtype``, ``spacing``, ``origin`` (see
            `volumes.io.load_file`).
    """
    spec = DEFAULT if spec is None else spec
    if isinstance(spec, str) and spec.startswith("synthetic:"):
        from isolume.volumes.synthetic import parse

        return parse(spec)
    from isolume.volumes.io import load_file

    return load_file(spec, **options)
