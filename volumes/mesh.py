"""Isosurface extraction: scikit-image marching cubes → `Mesh` in world units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage import measure

from .core import Volume, VolumeError
from .field import gradient_at, normals_from_gradient


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in world units.

    Attributes:
        vertices: (V, 3) float32 world xyz.
        faces: (F, 3) uint32 vertex indices.
        normals: (V, 3) float32 unit normals, high → low values (see `volumes.field`);
            (0, 3) when extracted with ``normals="none"`` (ray-tracing scenes need none).
        iso: the isovalue it was extracted at.
        message: why the mesh is empty, or "".
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    iso: float
    message: str = ""

    @property
    def empty(self) -> bool:
        """True when the mesh has no triangles."""
        return len(self.faces) == 0

    @staticmethod
    def empty_at(iso: float, message: str) -> Mesh:
        """An empty mesh that says why it is empty."""
        return Mesh(
            np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32),
            np.zeros((0, 3), np.float32), iso, message,
        )


def check_isovalue(volume: Volume, iso: float) -> float:
    """Return `iso` as float, or raise VolumeError when it lies outside the data range."""
    lo, hi = volume.value_range
    iso = float(iso)
    if not np.isfinite(iso) or iso < lo or iso > hi:
        raise VolumeError(
            f"{volume.source or volume.name}: isovalue {iso:g} is outside the data range "
            f"[{lo:g}, {hi:g}]"
        )
    return iso


def isosurface(
    volume: Volume,
    iso: float,
    *,
    normals: str = "smooth",
    flip_normals: bool = False,
    step_size: int = 1,
    keep_degenerate: bool = False,
) -> Mesh:
    """Extract the isosurface ρ = iso.

    Args:
        volume: the scalar field.
        iso: isovalue; must lie in the data range (else VolumeError).
        normals: "smooth" (tricubic-B-spline gradient, the paper's), "gradient" (plain
            central differences) or "none" (no normals: a mesh for ray tracing only).
        flip_normals: reverse the normals (for data whose material is less dense).
        step_size: marching-cubes step in voxels (2 gives a fast coarse preview).
        keep_degenerate: keep zero-area triangles (ray tracing never hits them; removing
            them costs a third of the marching cubes).

    Returns:
        Mesh in world units; an empty mesh with a message when the surface is empty
        (e.g. iso equal to the minimum or maximum, or a constant volume).
    """
    if normals not in ("smooth", "gradient", "none"):
        raise ValueError(f"normals must be 'smooth', 'gradient' or 'none', got {normals!r}")
    iso = check_isovalue(volume, iso)
    lo, hi = volume.value_range
    if not lo < iso < hi:
        return Mesh.empty_at(iso, f"isovalue {iso:g} is at the data's extreme; nothing to show")
    try:
        verts, faces, _, _ = measure.marching_cubes(
            volume.data, level=iso, step_size=step_size, allow_degenerate=keep_degenerate
        )
    except ValueError:  # the strided samples (step_size > 1) all lie on one side of iso
        return Mesh.empty_at(iso, f"no surface at isovalue {iso:g} at step size {step_size}")
    if len(faces) == 0:
        return Mesh.empty_at(iso, f"no surface at isovalue {iso:g}")
    world = volume.index_to_world(verts)
    if normals == "none":
        n = np.zeros((0, 3), np.float32)
    else:
        n, _ = normals_from_gradient(gradient_at(volume, world, smooth=normals == "smooth"),
                                     flip=flip_normals)
    return Mesh(world.astype(np.float32), faces.astype(np.uint32), n, iso)
