"""Marching cubes without the GIL, for the surfaces only rays see (the baker's levels).

scikit-image's marching cubes (`volumes.isosurface`, what the renderer draws) holds the
GIL for a whole call — 0.17 s on the engine CT — and the baker builds its level scenes on a
helper thread beside the plan and the tracing, whose Python and numpy steps then wait. This
is the classic algorithm as compiled passes over z-slabs on threads (count, then fill),
giving an indexed mesh with one vertex per crossed grid edge (a soup with three vertices
per triangle would hold 36 bytes a triangle where this holds about 6) and no normals (a
ray tracer needs none).

The case table is derived here, not copied: for each of the 256 sign patterns of a cell's
corners, the edges whose ends lie on opposite sides of the isovalue are joined face by face
(on a face with two crossed edges, those two; on an ambiguous face — inside corners
diagonal — each inside corner is cut off on its own), the face segments close into loops,
and each loop is fanned into triangles. The rule on a face depends on that face's four
corners only, so the two cells sharing it cut it the same way, and an edge's vertex is
interpolated from the same two samples in the same order in both: the mesh is watertight
(tested). On ambiguous faces it may join what Lewiner's variant separates, or the reverse;
both are piecewise-linear approximations of the same trilinear level set.
"""

from __future__ import annotations

import functools

import numba
import numpy as np
import numpy.typing as npt

from isolume.volumes import cores
from isolume.volumes.core import Volume

_EDGES = np.array([(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit])
"""(12, 2) corner pairs of the cell's edges, lower corner first (corner c = x + 2y + 4z)."""
_FACES = [[c for c in range(8) if bool(c & bit) == side] for bit in (1, 2, 4)
          for side in (False, True)]
"""The 6 faces as their 4 corners."""


@functools.cache
def case_table() -> tuple[np.ndarray, np.ndarray]:
    """Triangles of every corner sign pattern.

    Returns:
        count: (256,) int64 triangles of case m (bit c set: corner c above the isovalue);
        edges: (256, 12, 3) int64 the edges (rows of `_EDGES`) of their vertices.
    """
    count = np.zeros(256, np.int64)
    edges = np.zeros((256, 12, 3), np.int64)
    for case in range(256):
        triangles = [tri for loop in _loops(case) for tri in _fan(loop)]
        count[case] = len(triangles)
        if triangles:
            edges[case, :len(triangles)] = triangles
    return count, edges


def _loops(case: int) -> list[list[int]]:
    """The closed loops of crossed edges of sign pattern `case` (see the module docs)."""
    inside = [bool(case >> c & 1) for c in range(8)]
    crossed = {e for e, (a, b) in enumerate(_EDGES) if inside[a] != inside[b]}
    links: dict[int, list[int]] = {e: [] for e in crossed}
    for face in _FACES:
        on_face = [e for e in crossed if set(_EDGES[e]) <= set(face)]
        if len(on_face) == 2:
            pairs = [on_face]
        else:  # four: cut off each inside corner of the face on its own
            pairs = [[e for e in on_face if c in _EDGES[e]] for c in face if inside[c]]
        for a, b in (p for p in pairs if len(p) == 2):
            links[a].append(b)
            links[b].append(a)
    loops, seen = [], set()
    for start in sorted(crossed):
        if start in seen:
            continue
        loop, previous, current = [start], None, start
        seen.add(start)
        while True:
            step = links[current][0] if links[current][0] != previous else links[current][1]
            if step == start:
                break
            loop.append(step)
            seen.add(step)
            previous, current = current, step
        loops.append(loop)
    return loops


def _fan(loop: list[int]) -> list[tuple[int, int, int]]:
    """Triangles fanning the polygon `loop` from its first vertex."""
    return [(loop[0], loop[i], loop[i + 1]) for i in range(1, len(loop) - 1)]


@numba.njit(nogil=True, cache=True)
def _case(data: np.ndarray, iso: float, k: int, j: int, i: int) -> int:
    """Sign pattern of cell (k, j, i): bit c set where corner c lies above `iso`."""
    case = 0
    for c in range(8):
        if data[k + (c >> 2), j + (c >> 1 & 1), i + (c & 1)] > iso:
            case |= 1 << c
    return case


@numba.njit(nogil=True, cache=True)
def _count(data: np.ndarray, iso: float, count: np.ndarray, k0: int, k1: int,
           totals: np.ndarray) -> None:
    """totals[k] = triangles of the cells in z-layer k, for k in [k0, k1)."""
    for k in range(k0, k1):
        total = 0
        for j in range(data.shape[1] - 1):
            for i in range(data.shape[2] - 1):
                total += count[_case(data, iso, k, j, i)]
        totals[k] = total


@numba.njit(nogil=True, cache=True, inline="always")
def _crossed(data: np.ndarray, iso: float, k: int, j: int, i: int, axis: int) -> bool:
    """Does the grid edge from (k, j, i) one step along `axis` (0: x, 1: y, 2: z) exist
    and cross `iso` (its ends on opposite sides, as `_case` tests them)?"""
    nz, ny, nx = data.shape
    xb, yb, zb = i + (axis == 0), j + (axis == 1), k + (axis == 2)
    if xb >= nx or yb >= ny or zb >= nz:
        return False
    return (data[k, j, i] > iso) != (data[zb, yb, xb] > iso)


@numba.njit(nogil=True, cache=True)
def _count_vertices(data: np.ndarray, iso: float, k0: int, k1: int,
                    totals: np.ndarray) -> None:
    """totals[k] = crossed edges owned by grid layer k (`_edge_map`), for k in [k0, k1)."""
    ny, nx = data.shape[1:]
    for k in range(k0, k1):
        total = 0
        for j in range(ny):
            for i in range(nx):
                for axis in range(3):
                    total += _crossed(data, iso, k, j, i, axis)
        totals[k] = total


@numba.njit(nogil=True, cache=True)
def _edge_map(data: np.ndarray, iso: float, k: int, first: int, index: np.ndarray,
              write: bool, origin: np.ndarray, spacing: np.ndarray,
              vertices: np.ndarray) -> None:
    """Number the crossed edges owned by grid layer k — those whose lower corner lies in
    it: along x and y within it, along z from it to k + 1 — from `first` on, in (j, i,
    axis) order, into index[j, i, axis] ((Y, X, 3) int64); where `write`, also their
    vertices into `vertices` ((V, 3) float32 world xyz), interpolated from the lower
    corner (the same arithmetic in every cell that shares the edge)."""
    ny, nx = data.shape[1:]
    v = first
    for j in range(ny):
        for i in range(nx):
            for axis in range(3):
                if not _crossed(data, iso, k, j, i, axis):
                    continue
                xb, yb, zb = i + (axis == 0), j + (axis == 1), k + (axis == 2)
                index[j, i, axis] = v
                if write:
                    va = np.float32(data[k, j, i])  # integers would wrap
                    vb = np.float32(data[zb, yb, xb])
                    f = (iso - va) / (vb - va)
                    vertices[v, 0] = origin[0] + (i + f * (xb - i)) * spacing[0]
                    vertices[v, 1] = origin[1] + (j + f * (yb - j)) * spacing[1]
                    vertices[v, 2] = origin[2] + (k + f * (zb - k)) * spacing[2]
                v += 1


@numba.njit(nogil=True, cache=True)
def _fill(data: np.ndarray, iso: float, count: np.ndarray, table: np.ndarray,
          corner_pairs: np.ndarray, origin: np.ndarray, spacing: np.ndarray,
          vertex_first: np.ndarray, k0: int, k1: int, vertices: np.ndarray,
          faces: np.ndarray, first: int) -> None:
    """Write the triangles of cell layers [k0, k1) into faces[first:] ((T, 3) int32
    indices into `vertices`), and the vertices of grid layers [k0, k1) — and of the last
    grid layer when k1 is the last cell layer — into `vertices` (`_edge_map`; grid layer
    k's are numbered from vertex_first[k] on)."""
    nz, ny, nx = data.shape
    lower = np.empty((ny, nx, 3), np.int64)
    upper = np.empty((ny, nx, 3), np.int64)
    _edge_map(data, iso, k0, vertex_first[k0], lower, True, origin, spacing, vertices)
    t = first
    for k in range(k0, k1):
        _edge_map(data, iso, k + 1, vertex_first[k + 1], upper, k + 1 < k1 or k + 1 == nz - 1,
                  origin, spacing, vertices)
        for j in range(ny - 1):
            for i in range(nx - 1):
                case = _case(data, iso, k, j, i)
                for n in range(count[case]):
                    for corner in range(3):
                        edge = table[case, n, corner]
                        a, b = corner_pairs[edge, 0], corner_pairs[edge, 1]
                        axis = (b - a) >> 1  # b − a is 1, 2 or 4: along x, y or z
                        y, x = j + (a >> 1 & 1), i + (a & 1)
                        faces[t, corner] = lower[y, x, axis] if (a >> 2) == 0 else \
                            upper[y, x, axis]
                    t += 1
        lower, upper = upper, lower


@numba.njit(nogil=True, cache=True)
def edge_crossings(layers: np.ndarray, axis: int, below: float, above: float,
                   levels: np.ndarray, k0: int, k1: int) -> np.ndarray:
    """Where the levels cross the grid edges along `axis` (0: z, 1: y, 2: x) of (K, Y, X)
    `layers` that start in layers [`k0`, `k1`): the edges whose ends a ≠ b have
    min(a, b) ≤ `above` and max(a, b) ≥ `below` (the range's ends in the comparisons'
    type), in C order of their lower ends.

    Returns:
        (L, N, 3) float64: for each of the (L,) `levels` (float64), the N edges' crossing
        points as voxel indices z, y, x in `layers`, placed where the level, clipped to
        the edge's values, lies between them linearly (a + t (b − a), as marching cubes
        places its vertices).
    """
    dk, dj, di = int(axis == 0), int(axis == 1), int(axis == 2)
    ny, nx = layers.shape[1] - dj, layers.shape[2] - di
    count = 0
    for k in range(k0, k1):
        for j in range(ny):
            for i in range(nx):
                a, b = layers[k, j, i], layers[k + dk, j + dj, i + di]
                count += (min(a, b) <= above) & (max(a, b) >= below) & (a != b)
    out = np.empty((len(levels), count, 3), np.float64)
    n = 0
    for k in range(k0, k1):
        for j in range(ny):
            for i in range(nx):
                a, b = layers[k, j, i], layers[k + dk, j + dj, i + di]
                if not ((min(a, b) <= above) & (max(a, b) >= below) & (a != b)):
                    continue
                fa, fb = np.float64(a), np.float64(b)
                lower, upper = min(fa, fb), max(fa, fb)
                for m in range(len(levels)):
                    out[m, n, 0], out[m, n, 1], out[m, n, 2] = k, j, i
                    out[m, n, axis] += (min(max(levels[m], lower), upper) - fa) / (fb - fa)
                n += 1
    return out


def tracing_surface(volume: Volume, iso: float) -> tuple[np.ndarray, np.ndarray]:
    """The isosurface ρ = `iso` as a watertight indexed triangle mesh for ray tracing,
    extracted without the GIL (see the module docs): a vertex per crossed grid edge,
    shared by the triangles of every cell around it.

    Returns:
        vertices: (V, 3) float32 world xyz; faces: (T, 3) int32 indices into them. Both
        empty where nothing crosses `iso`.
    """
    count, table = case_table()
    data = np.ascontiguousarray(volume.data)  # the kernels compile for its type
    grid_layers = data.shape[0]
    layers = max(grid_layers - 1, 0)
    cells_per_layer = max(data.shape[1] - 1, 0) * max(data.shape[2] - 1, 0)
    totals = np.zeros(layers, np.int64)
    cores.for_ranges(lambda lo, hi: _count(data, float(iso), count, lo, hi, totals), layers,
                     cells_per_layer, "surface")
    if layers == 0 or totals.sum() == 0:
        return padded_empty((0, 3), np.float32), padded_empty((0, 3), np.int32)
    crossed = np.zeros(grid_layers, np.int64)
    cores.for_ranges(lambda lo, hi: _count_vertices(data, float(iso), lo, hi, crossed),
                     grid_layers, 3 * data.shape[1] * data.shape[2], "surface")
    firsts = np.concatenate([[0], np.cumsum(totals)])
    vertex_first = np.concatenate([[0], np.cumsum(crossed)])
    vertices = padded_empty((int(vertex_first[-1]), 3), np.float32)
    faces = padded_empty((int(firsts[-1]), 3), np.int32)
    origin = np.asarray(volume.origin, np.float64)
    spacing = np.asarray(volume.spacing, np.float64)

    def fill_layers(lo: int, hi: int) -> None:
        _fill(data, float(iso), count, table, _EDGES, origin, spacing, vertex_first, lo, hi,
              vertices, faces, int(firsts[lo]))

    cores.for_ranges(fill_layers, layers, cells_per_layer, "surface")
    return vertices, faces


PAD_BYTES = 16
"""Bytes allocated past the end of a surface's arrays: Embree shares them
(`baking.trace.padded`) and reads 16 bytes at a time, up to the last element's end."""


def padded_empty(shape: tuple[int, ...], dtype: npt.DTypeLike) -> np.ndarray:
    """An uninitialised (N, 3) array followed by `PAD_BYTES` more in its buffer."""
    n = int(np.prod(shape))
    flat = np.empty(n + -(-PAD_BYTES // np.dtype(dtype).itemsize), dtype)
    return flat[:n].reshape(shape)


def padded_copy(array: np.ndarray, dtype: npt.DTypeLike) -> np.ndarray:
    """`array` as `dtype` in a buffer with `PAD_BYTES` more after it."""
    out = padded_empty(array.shape, dtype)
    out[...] = array
    return out
