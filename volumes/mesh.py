"""Isosurface extraction: compiled marching cubes (`volumes.cubes`) → `Mesh` in world
units."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from isolume.volumes import cores
from isolume.volumes.core import Volume, VolumeError
from isolume.volumes.cubes import edge_crossings, marching_cubes, padded_copy, welded
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


def check_isovalue(volume: Volume, iso: float) -> float:
    """Return `iso` as float, or raise VolumeError when it lies outside the data range."""
    lo, hi = volume.value_range
    iso = float(iso)
    if not np.isfinite(iso):
        raise VolumeError(f"{volume.source or volume.name}: isovalue {iso:g}: expected a "
                          f"finite number within the data range [{lo:g}, {hi:g}]")
    if iso < lo or iso > hi:
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
    cancelled: Callable[[], bool] | None = None,
) -> Mesh | None:
    """Extract the isosurface ρ = iso (`volumes.cubes.marching_cubes`, on every core
    without the GIL; triangles facing from high to low values, as the normals do).

    Args:
        volume: the scalar field.
        iso: isovalue; must lie in the data range (else VolumeError).
        normals: "smooth" (tricubic-B-spline gradient, the paper's), "gradient" (plain
            central differences) or "none" (no normals: a mesh for ray tracing only).
        flip_normals: reverse the normals (for data whose material is less dense).
        step_size: marching-cubes step in voxels: the cubes of every step-th sample along
            each axis (2 gives a fast coarse preview).
        keep_degenerate: keep the zero-area triangles around samples exactly at `iso`
            (ray tracing never hits them), and their vertices apart; else those vertices
            are joined and the triangles dropped (`volumes.cubes.welded`).
        cancelled: asked during the marching cubes; True abandons the work.

    Returns:
        Mesh in world units; an empty mesh with a message when the surface is empty
        (e.g. iso equal to the minimum or maximum, or a constant volume); None when
        cancelled.
    """
    if normals not in ("smooth", "gradient", "none"):
        raise ValueError(f"normals must be 'smooth', 'gradient' or 'none', got {normals!r}")
    if step_size < 1:
        raise ValueError(f"step_size must be at least 1, got {step_size}")
    iso = check_isovalue(volume, iso)
    lo, hi = volume.value_range
    if not lo < iso < hi:
        return Mesh.empty_at(iso, f"isovalue {iso:g} is at the data's extreme; nothing to show")
    data = volume.data[::step_size, ::step_size, ::step_size]
    surface = marching_cubes(data, iso, volume.origin, np.multiply(volume.spacing, step_size),
                             cancelled=cancelled)
    if surface is None:
        return None
    if len(surface.faces) == 0:
        at_step = f" at step size {step_size}" if step_size > 1 else ""
        return Mesh.empty_at(iso, f"no surface at isovalue {iso:g}{at_step}")
    vertices, faces = surface.vertices, surface.faces
    if surface.at_iso and not keep_degenerate:
        vertices, faces = (padded_copy(a, a.dtype) for a in welded(vertices, faces))
    if normals == "none":
        n = np.zeros((0, 3), np.float32)
    else:
        n, _ = normals_from_gradient(gradient_at(volume, vertices.astype(np.float64),
                                                 smooth=normals == "smooth"),
                                     flip=flip_normals)
    # with room after them, so that Embree can share them (`baking.trace.padded`)
    return Mesh(vertices, faces.view(np.uint32), n, iso)


LEVEL_SLAB = 32
"""z layers of the volume after which `level_points` thins the points it keeps."""

SLAB_THREADS = 8
"""Threads per slab whose crossings `level_points` finds at once (a slab is 24 items): its
memory is the crossings of threads / 8 slabs, up to 144 bytes a voxel (an isovalue range
crossed everywhere: three edges, two levels, 24 bytes a point), and a part's copy as
its items are joined."""

LEVEL_POINTS = 100_000
"""At most this many points from `level_points` (spread evenly over the crossings)."""

LEVEL_ITEM = 4
"""z layers of one work item of `level_points`."""


def level_points(volume: Volume, lo: float, hi: float | None = None,
                 limit: int = LEVEL_POINTS) -> np.ndarray:
    """World points of the isosurfaces at the isovalues `lo`..`hi` (`hi` None: `lo`
    alone): where a level in that range crosses an edge between two neighbouring samples,
    placed by linear interpolation as marching cubes places its vertices (at both ends of
    the range). Every crossing up to `limit` of them, else a random subset (the same each
    time, and on any number of threads; a regular stride would alias with the grid).

    The crossings are found by a compiled kernel (`cubes.edge_crossings`) in items of
    `LEVEL_ITEM` z layers on every core, a slab of `LEVEL_SLAB` layers for every
    `SLAB_THREADS` threads at a time; the slabs are thinned in order.

    Returns:
        (N, 3) float64 world xyz, N ≤ `limit`; (0, 3) when no level in the range crosses.
    """
    lo = float(lo)
    hi = lo if hi is None else float(hi)
    data = volume.data
    rng = np.random.default_rng(0)
    found: list[np.ndarray] = []
    kept, rate = 0, 1.0
    slabs = list(range(0, data.shape[0] - 1, LEVEL_SLAB))
    wave = -(-cores.threads() // SLAB_THREADS)
    for first in range(0, len(slabs), wave):
        for k0, parts in zip(slabs[first:first + wave],
                             _slab_crossings(data, slabs[first:first + wave], lo, hi),
                             strict=True):
            for points in parts:
                if rate < 1.0:
                    points = points[rng.random(len(points)) < rate]
                points[:, 0] += k0
                found.append(points)
                kept += len(points)
            if kept > 2 * limit:  # thin out what was kept, and what is to come, alike
                points = np.concatenate(found)
                found = [points[rng.random(len(points)) < 0.5]]
                kept, rate = len(found[0]), rate / 2
    zyx = np.concatenate(found) if found else np.zeros((0, 3))
    if len(zyx) > limit:
        zyx = zyx[np.sort(rng.choice(len(zyx), limit, replace=False))]
    return volume.index_to_world(zyx)


def _slab_crossings(data: np.ndarray, starts: list[int], lo: float, hi: float
                    ) -> list[list[np.ndarray]]:
    """For each slab of `LEVEL_SLAB` z layers of (Z, Y, X) `data` starting at `starts`,
    its three (M, 3) arrays of crossing points (voxel indices z, y, x from the slab's first
    layer) of the edges along z, y and x: two points per edge crossed by the range (all
    at `lo`, then all at `hi`), one where `lo` = `hi`. Found in items of `LEVEL_ITEM`
    layers on every core."""
    levels = np.array([lo] if lo == hi else [lo, hi])
    below, above = ((float(data.dtype.type(lo)), float(data.dtype.type(hi)))
                    if np.issubdtype(data.dtype, np.floating) else (lo, hi))  # as numpy's
    parts = []
    for k0 in starts:
        k1 = min(k0 + LEVEL_SLAB, data.shape[0] - 1)
        # z edges k0..k1; the edges within a layer: layers k0..k1-1 (and the last layer
        # with the last slab)
        layers = data[k0:k1 + 1] if k1 == data.shape[0] - 1 else data[k0:k1]
        parts += [(data[k0:k1 + 1], 0, k1 - k0), (layers, 1, len(layers)),
                  (layers, 2, len(layers))]
    items = [(p, a) for p, (_, _, n) in enumerate(parts) for a in range(0, n, LEVEL_ITEM)]
    found: list[np.ndarray | None] = [None] * len(items)

    def item(i: int) -> None:
        part, a = items[i]
        layers, axis, n = parts[part]
        found[i] = edge_crossings(layers, axis, below, above, levels, a,
                                  min(a + LEVEL_ITEM, n))

    cores.for_items(item, len(items), "framing")
    out = []
    for p in range(len(parts)):
        mine = [i for i, (part, _) in enumerate(items) if part == p]
        out.append(np.concatenate([found[i][m] for m in range(len(levels)) for i in mine])
                   if mine else np.zeros((0, 3)))
        for i in mine:  # its items' copies go as the part is joined
            found[i] = None
    return [out[3 * s:3 * s + 3] for s in range(len(starts))]
