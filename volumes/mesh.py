"""Isosurface extraction: scikit-image marching cubes → `Mesh` in world units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage import measure

from isolume.volumes.core import Volume, VolumeError
from isolume.volumes.field import gradient_at, normals_from_gradient


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


def marching_cubes(data: np.ndarray, iso: float, *, step_size: int = 1,
                   keep_degenerate: bool = False, slab_voxels: int | None = None,
                   cancelled=None) -> tuple[np.ndarray, np.ndarray] | None:
    """scikit-image's marching cubes of the (Z, Y, X) `data` at `iso`, whole or in z-slabs.

    scikit-image holds the GIL for a whole call (0.17 s on the engine CT's 8.4 M voxels),
    stalling every other Python thread — the bake's tracing workers among them. In slabs of
    about `slab_voxels` voxels the other threads run between slabs, slabs whose values miss
    `iso` are skipped, and `cancelled()` (asked between slabs) can abandon the work. The
    triangles are those of the whole call; vertices on slab boundaries appear once per slab
    at identical positions (the same edge interpolation), so the mesh stays watertight.

    Returns:
        vertices: (V, 3) float32 fractional voxel indices (z, y, x); faces: (F, 3) int
        (both empty when nothing crosses `iso`); or None when cancelled.
    """
    nz, ny, nx = data.shape
    thick = nz if slab_voxels is None else \
        max(step_size, (slab_voxels // (ny * nx)) // step_size * step_size)
    parts_v, parts_f, count = [], [], 0
    for z0 in range(0, max(nz - 1, 1), thick):
        if cancelled is not None and cancelled():
            return None
        block = data[z0:min(z0 + thick, nz - 1) + 1]
        if slab_voxels is not None and (block.min() > iso or block.max() < iso):
            continue
        try:
            v, f, _, _ = measure.marching_cubes(block, level=iso, step_size=step_size,
                                                allow_degenerate=keep_degenerate)
        except (ValueError, RuntimeError):  # the strided samples (step_size > 1) all lie on
            continue  # one side of iso, or a slab thinner than the step
        v[:, 0] += z0
        parts_v.append(v)
        parts_f.append(f + count)
        count += len(v)
    if not parts_f:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    return np.concatenate(parts_v), np.concatenate(parts_f)


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
    verts, faces = marching_cubes(volume.data, iso, step_size=step_size,
                                  keep_degenerate=keep_degenerate)
    if len(faces) == 0:
        at_step = f" at step size {step_size}" if step_size > 1 else ""
        return Mesh.empty_at(iso, f"no surface at isovalue {iso:g}{at_step}")
    world = volume.index_to_world(verts)
    if normals == "none":
        n = np.zeros((0, 3), np.float32)
    else:
        n, _ = normals_from_gradient(gradient_at(volume, world, smooth=normals == "smooth"),
                                     flip=flip_normals)
    return Mesh(world.astype(np.float32), faces.astype(np.uint32), n, iso)
