"""Marching cubes without the GIL, for the surfaces only rays see (the baker's levels).

scikit-image's marching cubes (`volumes.isosurface`, what the renderer draws) holds the
GIL for a whole call — 0.17 s on the engine CT — and the baker builds its level scenes on a
helper thread beside the plan and the tracing, whose Python and numpy steps then wait. This
is the classic algorithm as two compiled passes over z-slabs on threads (count, then fill),
giving a triangle soup: Embree needs no shared vertices, and a ray tracer no normals.

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

from isolume.volumes.core import Volume
from isolume.volumes.field import on_threads

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


@numba.njit(nogil=True, cache=True)
def _fill(data: np.ndarray, iso: float, count: np.ndarray, table: np.ndarray,
          corner_pairs: np.ndarray, origin: np.ndarray, spacing: np.ndarray, k0: int,
          k1: int, out: np.ndarray, first: int) -> None:
    """Write the triangles of z-layers [k0, k1) as world xyz vertices into out[3·first:]
    ((3T, 3) float32). An edge's vertex is interpolated from its lower corner."""
    v = 3 * first
    for k in range(k0, k1):
        for j in range(data.shape[1] - 1):
            for i in range(data.shape[2] - 1):
                case = _case(data, iso, k, j, i)
                for t in range(count[case]):
                    for corner in range(3):
                        edge = table[case, t, corner]
                        a, b = corner_pairs[edge, 0], corner_pairs[edge, 1]
                        za, ya, xa = k + (a >> 2), j + (a >> 1 & 1), i + (a & 1)
                        zb, yb, xb = k + (b >> 2), j + (b >> 1 & 1), i + (b & 1)
                        va = np.float32(data[za, ya, xa])  # integers would wrap
                        vb = np.float32(data[zb, yb, xb])
                        f = (iso - va) / (vb - va)
                        out[v, 0] = origin[0] + (xa + f * (xb - xa)) * spacing[0]
                        out[v, 1] = origin[1] + (ya + f * (yb - ya)) * spacing[1]
                        out[v, 2] = origin[2] + (za + f * (zb - za)) * spacing[2]
                        v += 1


def tracing_surface(volume: Volume, iso: float) -> tuple[np.ndarray, np.ndarray]:
    """The isosurface ρ = `iso` as a watertight triangle soup for ray tracing, extracted
    without the GIL (see the module docs).

    Returns:
        vertices: (3T, 3) float32 world xyz, three per triangle; faces: (T, 3) int32
        (row t is 3t, 3t + 1, 3t + 2). Both empty where nothing crosses `iso`.
    """
    count, table = case_table()
    data = np.ascontiguousarray(volume.data)  # the kernels compile for its type
    layers = max(data.shape[0] - 1, 0)
    cells_per_layer = max(data.shape[1] - 1, 0) * max(data.shape[2] - 1, 0)
    totals = np.zeros(layers, np.int64)

    on_threads(lambda lo, hi: _count(data, float(iso), count, lo, hi, totals), layers,
                cells_per_layer)
    firsts = np.concatenate([[0], np.cumsum(totals)])
    vertices = padded_empty((3 * int(firsts[-1]), 3), np.float32)
    origin = np.asarray(volume.origin, np.float64)
    spacing = np.asarray(volume.spacing, np.float64)

    def fill_layers(lo: int, hi: int) -> None:
        _fill(data, float(iso), count, table, _EDGES, origin, spacing, lo, hi, vertices,
              int(firsts[lo]))

    on_threads(fill_layers, layers, cells_per_layer)
    faces = padded_empty((len(vertices) // 3, 3), np.int32)
    faces.reshape(-1)[:] = np.arange(len(vertices), dtype=np.int32)
    return vertices, faces


PAD_BYTES = 16
"""Bytes allocated past the end of a surface's arrays: Embree shares them
(`baking.trace.padded`) and reads 16 bytes at a time, up to the last element's end."""


def padded_empty(shape: tuple[int, int], dtype) -> np.ndarray:
    """An uninitialised (N, 3) array followed by `PAD_BYTES` more in its buffer."""
    n = int(np.prod(shape))
    flat = np.empty(n + -(-PAD_BYTES // np.dtype(dtype).itemsize), dtype)
    return flat[:n].reshape(shape)


def padded_copy(array: np.ndarray, dtype) -> np.ndarray:
    """`array` as `dtype` in a buffer with `PAD_BYTES` more after it."""
    out = padded_empty(array.shape, dtype)
    out[...] = array
    return out
