"""Marching cubes without the GIL: every isosurface isolume draws, traces or exports.

scikit-image's marching cubes holds the GIL for a whole call (0.17 s on the engine CT),
so a surface made beside other work (the viewer's isovalue drags beside its frames, the
baker's level scenes beside its tracing) would stall every Python thread, and a
command's surface would run on one core. This is the classic algorithm as compiled passes
over z-slabs on every core (count, then fill), giving an indexed mesh with one vertex per
crossed grid edge (a soup with three vertices per triangle would hold 36 bytes a triangle
where this holds about 6).

The case table is derived here, not copied: for each of the 256 sign patterns of a cell's
corners, the edges whose ends lie on opposite sides of the isovalue are joined face by face
(on a face with two crossed edges, those two; on an ambiguous face — the corners above the
isovalue diagonal — each corner above is cut off on its own, or, in the drawn table where
the face's bilinear interpolant joins them across it, each corner below), the face
segments close into loops, and each loop is cut into triangles. The rule on a face depends
on that face's four samples only, so the two cells sharing it cut it the same way, and an
edge's vertex is interpolated from the same two samples in the same order in both: the
mesh is watertight (tested). Lewiner's variant (scikit-image's) also decides each cell's
interior, which this does not; both are piecewise-linear approximations of the same
trilinear level set, with the same vertices (tested against scikit-image), and on the
Marschner–Lobb signal the drawn surface lies as close to it as scikit-image's (1.05× the
mean distance), the baker's 1.65× as far.

Drawn surfaces (`volumes.isosurface`: shown, exported, path-traced for references) decide
the ambiguous faces, triangulate each loop without a triangle in a face of the cell, and
turn its triangles to face from the samples above the isovalue to those below, as the
normals of `volumes.field` do. The baker's level scenes keep the plain table (each corner
above cut off, each loop fanned in its order): their hits stay those their lattices were
recorded with, and a ray tracer needs no winding.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np
import numpy.typing as npt

from isolume.volumes import cores
from isolume.volumes.core import Volume
from isolume.volumes.errors import WriteError
from isolume.volumes.writing import atomic_write

_EDGES = np.array([(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit])
"""(12, 2) corner pairs of the cell's edges, lower corner first (corner c = x + 2y + 4z)."""
_FACES = [[c for c in range(8) if bool(c & bit) == side] for bit in (1, 2, 4)
          for side in (False, True)]
"""The 6 faces as their 4 corners, in order of corner number: the first and the last lie
diagonally across the face, as do the middle two."""
_FACE_CORNERS = np.array(_FACES)
"""(6, 4) `_FACES` for the kernels."""
_EDGE_FACES = [sum(1 << f for f, face in enumerate(_FACES) if set(map(int, ends)) <= set(face))
               for ends in _EDGES]
"""(12,) the faces (bit f of `_FACES`) that each edge lies in."""


class CaseTable(NamedTuple):
    """Triangles of every corner sign pattern and choice on its ambiguous faces.

    Attributes:
        count: (256, 64) int64 triangles of case m (bit c set: corner c above the
            isovalue) with the choices j (bit f set: on face f of `_FACES`, where it is
            ambiguous, the corners above the isovalue are joined across it).
        edges: (256, 64, 12, 3) int8 the edges (rows of `_EDGES`) of their vertices.
        ambiguous: (256,) int64 the faces (bit f) of case m whose corners above the
            isovalue lie diagonally, where a cell's marching cubes chooses (all zero in
            a table that does not choose: each corner above is cut off on its own).
    """

    count: np.ndarray
    edges: np.ndarray
    ambiguous: np.ndarray


@functools.cache
def case_table(drawn: bool = False) -> CaseTable:
    """Triangles of every corner sign pattern (see the module docs). The baker's table
    (not `drawn`) fans each loop from its first edge, in the loop's order, and cuts off
    each corner above the isovalue on an ambiguous face. The `drawn` table joins them
    across an ambiguous face where the face's bilinear interpolant does (`_choices`),
    triangulates each loop without a triangle in a face of the cell (`_triangles`: two
    cells would both draw it) and turns its triangles so that their normals
    ((b − a) × (c − a)) point from the corners above the isovalue to those below
    (`facing`).

    Deriving the drawn table takes ~0.07 s of Python, so it is kept beside the compiled
    kernels (`kept_table`) and read from there (~2 ms) by later processes.
    """
    kept = kept_table(drawn)
    if kept is not None:
        try:
            with np.load(kept) as arrays:
                return CaseTable(*(arrays[name] for name in CaseTable._fields))
        except (OSError, KeyError, ValueError):
            pass  # missing or unreadable: derived again, and written again
    table = derived_table(drawn)
    if kept is not None:
        _keep(kept, table)
    return table


def derived_table(drawn: bool) -> CaseTable:
    """`case_table`, derived from the cell's geometry."""
    count = np.zeros((256, 64), np.int64)
    edges = np.zeros((256, 64, 12, 3), np.int8)
    ambiguous = np.array([_ambiguous_faces(case) if drawn else 0 for case in range(256)])
    for case in range(256):
        for joined in range(64):
            if joined & ~ambiguous[case]:
                continue  # the same as without the choices on faces that offer none
            triangles = [t for loop in _loops(case, joined)
                         for t in (_drawn_triangles(loop, case) if drawn else _fan(loop))]
            same = [c for c in range(64) if c & ambiguous[case] == joined]
            count[case, same] = len(triangles)
            if triangles:
                edges[case, same, :len(triangles)] = triangles
    return CaseTable(count, edges, ambiguous)


def kept_table(drawn: bool) -> Path | None:
    """Where `case_table(drawn)` is kept: in this module's ``__pycache__`` (where numba
    keeps its compiled kernels), named by a digest of this module's source, so that a
    changed module derives it again; None where the source cannot be read."""
    try:
        source = Path(__file__).read_bytes()
    except OSError:
        return None
    digest = hashlib.sha256(source).hexdigest()[:16]
    kind = "drawn" if drawn else "traced"
    return Path(__file__).parent / "__pycache__" / f"cubes.{kind}-table.{digest}.npz"


def _keep(path: Path, table: CaseTable) -> None:
    """Write `table` to `path` whole (`volumes.writing.atomic_write`), in place of the
    tables an earlier source of this module kept, or nowhere where the folder cannot be
    written."""
    try:
        path.parent.mkdir(exist_ok=True)
        atomic_write(path, lambda tmp: np.savez(tmp, **table._asdict()), "case table")
        kind = path.name.split(".")[1]
        for old in path.parent.glob(f"cubes.{kind}.*.npz"):
            if old != path:
                old.unlink(missing_ok=True)
    except (OSError, WriteError):
        return


def _ambiguous_faces(case: int) -> int:
    """The faces (bit f of `_FACES`) of sign pattern `case` whose corners above the
    isovalue lie diagonally across them."""
    faces = 0
    for f, (a, b, c, d) in enumerate(_FACES):
        above = [bool(case >> corner & 1) for corner in (a, b, c, d)]
        if above[0] == above[3] and above[1] == above[2] and above[0] != above[1]:
            faces |= 1 << f
    return faces


def _loops(case: int, joined: int = 0) -> list[list[int]]:
    """The closed loops of crossed edges of sign pattern `case`, the corners above the
    isovalue joined across the ambiguous faces in `joined` (bit f of `_FACES`) and cut
    off one by one on the others (see the module docs)."""
    inside = [bool(case >> c & 1) for c in range(8)]
    ends = [(int(a), int(b)) for a, b in _EDGES]
    crossed = {e for e, (a, b) in enumerate(ends) if inside[a] != inside[b]}
    links: dict[int, list[int]] = {e: [] for e in crossed}
    for f, face in enumerate(_FACES):
        on_face = [e for e in range(12) if e in crossed and _EDGE_FACES[e] >> f & 1]
        if len(on_face) == 2:
            pairs = [on_face]
        else:  # four: cut off each corner on the side not joined across the face
            cut = [inside[c] != bool(joined >> f & 1) for c in range(8)]
            pairs = [[e for e in on_face if c in ends[e]] for c in face if cut[c]]
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


def _corner_position(c: int) -> tuple[int, int, int]:
    """x, y, z of corner c of the unit cell."""
    return c & 1, c >> 1 & 1, c >> 2 & 1


_MIDPOINTS = [tuple((u + v) / 2 for u, v in zip(_corner_position(int(a)),
                                               _corner_position(int(b)), strict=True))
              for a, b in _EDGES]
"""(12,) x, y, z of the edges' midpoints in the unit cell."""
_DIRECTIONS = [tuple(v - u for u, v in zip(_corner_position(int(a)), _corner_position(int(b)),
                                           strict=True)) for a, b in _EDGES]
"""(12,) each edge's step from its lower corner to its upper one."""


def in_a_face(*edges: int) -> bool:
    """Do the vertices of `edges` (their crossings) lie in one face of the cell?"""
    shared = 63
    for e in edges:
        shared &= _EDGE_FACES[e]
    return bool(shared)


def _fan(loop: list[int]) -> list[tuple[int, int, int]]:
    """Triangles fanning the polygon `loop` from its first vertex."""
    return [(loop[0], loop[i], loop[i + 1]) for i in range(1, len(loop) - 1)]


def _triangles(loop: list[int]) -> list[tuple[int, int, int]]:
    """The polygon `loop` in triangles, in its order, with as few diagonals lying in a
    face of the cell as there can be (the cell across that face has the face's crossings
    in its own loops, and a diagonal there can pinch the surface against it; on the drawn
    table's loops none up to 7 edges, at most two, tested): its fan where that has none, else a
    triangulation found by dynamic programming over the polygon's triangulations."""
    n = len(loop)

    def cost(i: int, j: int) -> int:
        """1 for a diagonal (not a side) of the polygon between vertices i < j lying in
        a face."""
        return int(1 < j - i < n - 1 and in_a_face(loop[i], loop[j]))

    if not any(cost(0, i) for i in range(2, n - 1)):
        return _fan(loop)

    @functools.cache
    def best(i: int, j: int) -> tuple[int, tuple[tuple[int, int, int], ...]]:
        """Fewest in-face diagonals over the triangulations of loop[i..j], and one."""
        if j - i < 2:
            return 0, ()
        choices = []
        for k in range(i + 1, j):
            (m, left), (r, right) = best(i, k), best(k, j)
            choices.append((m + r + cost(i, k) + cost(k, j),
                            left + right + ((loop[i], loop[k], loop[j]),)))
        return min(choices, key=lambda choice: choice[0])

    return list(best(0, n - 1)[1])


def facing(triangles: list[tuple[int, int, int]], case: int) -> float:
    """How `triangles` (of crossed edges of sign pattern `case`, through the edges'
    midpoints) face: the sum of their normals dotted with their three edges' steps from
    the corner above the isovalue to the one below; > 0 where they face downhill. (A
    loop's own normal, by Newell's rule, cancels on the saddle-shaped loops of joined
    faces; this sum is nonzero on every loop, tested.)"""
    total = 0.0
    for a, b, c in triangles:
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = _MIDPOINTS[a], _MIDPOINTS[b], _MIDPOINTS[c]
        ux, uy, uz, vx, vy, vz = bx - ax, by - ay, bz - az, cx - ax, cy - ay, cz - az
        steps = [0, 0, 0]
        for e in (a, b, c):
            sign = 1 if case >> int(_EDGES[e, 0]) & 1 else -1  # from above to below
            steps = [s + sign * d for s, d in zip(steps, _DIRECTIONS[e], strict=True)]
        total += ((uy * vz - uz * vy) * steps[0] + (uz * vx - ux * vz) * steps[1]
                  + (ux * vy - uy * vx) * steps[2])
    return total


def _drawn_triangles(loop: list[int], case: int) -> list[tuple[int, int, int]]:
    """The drawn table's triangles of `loop`: `_triangles`, turned where they face
    uphill (`facing`)."""
    triangles = _triangles(loop)
    if facing(triangles, case) > 0:
        return triangles
    return [(a, c, b) for a, b, c in triangles]


@numba.njit(nogil=True, cache=True)
def _case(data: np.ndarray, iso: float, k: int, j: int, i: int) -> int:
    """Sign pattern of cell (k, j, i): bit c set where corner c lies above `iso`."""
    case = 0
    for c in range(8):
        if data[k + (c >> 2), j + (c >> 1 & 1), i + (c & 1)] > iso:
            case |= 1 << c
    return case


@numba.njit(nogil=True, cache=True, inline="always")
def _corner_value(data: np.ndarray, k: int, j: int, i: int, c: int) -> float:
    """Corner c of cell (k, j, i) as float64."""
    return np.float64(data[k + (c >> 2), j + (c >> 1 & 1), i + (c & 1)])


@numba.njit(nogil=True, cache=True, inline="always")
def _choices(data: np.ndarray, iso: float, k: int, j: int, i: int, faces: int,
             corners: np.ndarray) -> int:
    """The ambiguous faces among `faces` (bit f of `_FACES`, whose (6, 4) corners are
    `corners`) of cell (k, j, i) across which its corners above `iso` are joined: where
    the face's bilinear interpolant at its saddle, (a·d − b·c) / (a + d − b − c) for
    corners a, d and b, c diagonally across, lies above `iso` (the asymptotic decider).
    Two cells sharing a face compute it from the same four samples in the same order."""
    joined = 0
    if faces == 0:
        return joined
    for f in range(6):
        if not faces >> f & 1:
            continue
        a = _corner_value(data, k, j, i, corners[f, 0])
        b = _corner_value(data, k, j, i, corners[f, 1])
        c = _corner_value(data, k, j, i, corners[f, 2])
        d = _corner_value(data, k, j, i, corners[f, 3])
        if (a * d - b * c) / (a + d - b - c) > iso:
            joined |= 1 << f
    return joined


@numba.njit(nogil=True, cache=True)
def _count(data: np.ndarray, iso: float, count: np.ndarray, ambiguous: np.ndarray,
           corners: np.ndarray, k0: int, k1: int, totals: np.ndarray) -> None:
    """totals[k] = triangles of the cells in z-layer k, for k in [k0, k1) (`CaseTable`)."""
    decided = ambiguous.any()
    for k in range(k0, k1):
        total = 0
        for j in range(data.shape[1] - 1):
            for i in range(data.shape[2] - 1):
                case = _case(data, iso, k, j, i)
                if decided:  # the same for every cell: the plain table's pass keeps its speed
                    total += count[case, _choices(data, iso, k, j, i, ambiguous[case],
                                                  corners)]
                else:
                    total += count[case, 0]
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
def _count_vertices(data: np.ndarray, iso: float, k0: int, k1: int, totals: np.ndarray,
                    at_iso: np.ndarray) -> None:
    """totals[k] = crossed edges owned by grid layer k (`_edge_map`), at_iso[k] = its
    samples exactly at `iso` (where the vertices of the crossed edges from a sample lie
    on it), for k in [k0, k1)."""
    ny, nx = data.shape[1:]
    for k in range(k0, k1):
        total, on = 0, 0
        for j in range(ny):
            for i in range(nx):
                on += data[k, j, i] == iso
                for axis in range(3):
                    total += _crossed(data, iso, k, j, i, axis)
        totals[k] = total
        at_iso[k] = on


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
          ambiguous: np.ndarray, corners: np.ndarray, corner_pairs: np.ndarray,
          origin: np.ndarray, spacing: np.ndarray,
          vertex_first: np.ndarray, k0: int, k1: int, vertices: np.ndarray,
          faces: np.ndarray, first: int) -> None:
    """Write the triangles of cell layers [k0, k1) (`CaseTable`) into faces[first:] ((T, 3) int32
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
                choices = _choices(data, iso, k, j, i, ambiguous[case], corners)
                for n in range(count[case, choices]):
                    for corner in range(3):
                        edge = table[case, choices, n, corner]
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


CELLS_PER_MICROSECOND = 256
"""Cells a counting pass of `marching_cubes` covers in about a microsecond, the unit of
work of `volumes.cores.for_ranges` (1.3–4.5 ns a cell measured): its items are then long
enough that the GIL, which a thread needs between them, is seldom waited for (the
viewer's render thread holds it through each GL call)."""
FILL_COST = 8
"""The filling pass's time a cell against a counting pass's (12 against 1.3–4.5 ns)."""


def marching_cubes(data: np.ndarray, iso: float, origin: npt.ArrayLike = (0.0, 0.0, 0.0),
                   spacing: npt.ArrayLike = (1.0, 1.0, 1.0), *, drawn: bool = True,
                   cancelled: Callable[[], bool] | None = None) -> Surface | None:
    """The isosurface ρ = `iso` of the (Z, Y, X) samples `data` (sample (k, j, i) at
    world `origin` + (i, j, k) · `spacing`) as an indexed triangle mesh, on every core
    without the GIL (see the module docs): a vertex per crossed grid edge, shared by the
    triangles of every cell around it. `drawn`: triangles facing from the samples above
    `iso` to those below, and the ambiguous faces decided by the data (`case_table`
    oriented and decided); else the table's own winding and rule (the baker's level
    scenes). `cancelled()`, asked between and within the passes, abandons the work.

    Returns:
        A `Surface` (both arrays empty where nothing crosses `iso`), or None when
        cancelled.
    """
    count, table, ambiguous = case_table(drawn)
    data = np.ascontiguousarray(data)  # the kernels compile for its type
    iso = float(iso)
    stop = cancelled or (lambda: False)
    grid_layers = data.shape[0]
    layers = max(grid_layers - 1, 0)
    cells_per_layer = max(data.shape[1] - 1, 0) * max(data.shape[2] - 1, 0)
    totals = np.zeros(layers, np.int64)
    layer_cost = max(1, cells_per_layer // CELLS_PER_MICROSECOND)
    cores.for_ranges(lambda lo, hi: stop() or _count(data, iso, count, ambiguous, _FACE_CORNERS,
                                                     lo, hi, totals),
                     layers, layer_cost, "surface")
    if stop():
        return None
    if layers == 0 or totals.sum() == 0:
        return Surface(padded_empty((0, 3), np.float32), padded_empty((0, 3), np.int32), 0)
    crossed = np.zeros(grid_layers, np.int64)
    at_iso = np.zeros(grid_layers, np.int64)
    cores.for_ranges(lambda lo, hi: stop() or _count_vertices(data, iso, lo, hi, crossed,
                                                              at_iso),
                     grid_layers, layer_cost, "surface")
    firsts = np.concatenate([[0], np.cumsum(totals)])
    vertex_first = np.concatenate([[0], np.cumsum(crossed)])
    vertices = padded_empty((int(vertex_first[-1]), 3), np.float32)
    faces = padded_empty((int(firsts[-1]), 3), np.int32)
    origin = np.asarray(origin, np.float64)
    spacing = np.asarray(spacing, np.float64)

    def fill_layers(lo: int, hi: int) -> None:
        if not stop():
            _fill(data, iso, count, table, ambiguous, _FACE_CORNERS, _EDGES, origin, spacing,
                  vertex_first, lo, hi, vertices, faces, int(firsts[lo]))

    cores.for_ranges(fill_layers, layers, FILL_COST * layer_cost, "surface")
    if stop():
        return None
    return Surface(vertices, faces, int(at_iso.sum()))


class Surface(NamedTuple):
    """A mesh from `marching_cubes`.

    Attributes:
        vertices: (V, 3) float32 world xyz, one per crossed grid edge.
        faces: (T, 3) int32 indices into them.
        at_iso: samples exactly at the isovalue. The vertices of the crossed edges from
            such a sample lie on it, one per edge, and the triangles between them have no
            area (`welded` joins them).
    """

    vertices: np.ndarray
    faces: np.ndarray
    at_iso: int


def tracing_surface(volume: Volume, iso: float) -> tuple[np.ndarray, np.ndarray]:
    """The isosurface ρ = `iso` of `volume` for the baker's level scenes: `marching_cubes`
    in the case table's own winding and rule.

    Returns:
        vertices: (V, 3) float32 world xyz; faces: (T, 3) int32 indices into them. Both
        empty where nothing crosses `iso`.
    """
    surface = marching_cubes(volume.data, iso, volume.origin, volume.spacing, drawn=False)
    assert surface is not None  # nothing cancels it
    return surface.vertices, surface.faces


def welded(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with the vertices at one position joined into one, the triangles left
    without area (two corners joined) dropped, and the vertices no triangle uses
    dropped.

    Args:
        vertices: (V, 3) float32; faces: (T, 3) integer indices into them.

    Returns:
        vertices: (V', 3) float32, in order of position; faces: (T', 3) int32 into them,
        in the order they came (T' ≤ T).
    """
    rows = np.ascontiguousarray(vertices, np.float32).view(np.dtype((np.void, 12))).ravel()
    _, first, joined = np.unique(rows, return_index=True, return_inverse=True)
    tri = joined.reshape(-1)[faces]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])]
    used = np.zeros(len(first), bool)
    used[tri] = True
    renumber = np.cumsum(used) - 1
    return vertices[first[used]], renumber[tri].astype(np.int32)


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
