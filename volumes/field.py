"""Sampling the scalar field: trilinear values and smoothed gradients / normals.

The paper's normals (§4.1.1) come from the gradient of the field smoothed with the
tricubic B-spline kernel (support 4×4×4 voxels). Here the field is taken as the uniform
cubic B-spline whose control points are the samples; its exact gradient at a voxel centre
is the separable product of the central difference ``[-1, 0, 1]/2`` along one axis and the
B-spline weights ``[1, 4, 1]/6`` along the other two, rounded to float32; between voxel
centres it is interpolated trilinearly, which is what the GPU would do with it as a
texture. The voxel gradients are computed where a lookup needs them (the eight around the
point, from the 4×4×4 samples around its cell) rather than stored for the whole volume: no
12 bytes per voxel, the same bits.

Normals point from high values to low values: ``n = -∇ρ / |∇ρ|`` (out of the material when
the material is denser than its surroundings); ``flip=True`` reverses them.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from isolume.volumes import cores
from isolume.volumes.core import Volume

JIT: dict[str, Any] = {"nogil": True, "cache": True, "error_model": "numpy"}
"""numba's options for every kernel (this module's and the baker's): no GIL held,
compiled once per machine (cached), numpy's floating-point error model (a float division
by zero gives ±inf or NaN instead of raising: a division that may raise is a branch that
keeps reference counting alive, `PART`). A cached kernel is checked against its own
module's file only, not against the modules it calls (`baking.plan_kernels` and
`baking.side_kernels` call this one's, `baking.kernels` `baking.sampling_kernels`,
`baking.sky_kernels` and `baking.embree_kernels`): after editing a kernel module, delete
the cached kernels (``*.nbi``, ``*.nbc`` in ``__pycache__``)."""

PART: dict[str, Any] = {**JIT, "inline": "always"}
"""The options of the helpers that compiled loops call per point: numba compiles them
into the loop. numba increments and decrements an array's reference count (an atomic
operation) where a function binds it, and drops such pairs only where nothing between
them calls a function that takes arrays or may raise: a helper called per point with
arrays, or a view such as ``out[i]`` handed to one, keeps them in the loop: 30 a normal
made `normals_at` take twice as long, and `value_at` 2.5 times. A loop that calls these
helpers takes no views per point either; ``tests/test_kernel_loops.py`` counts what the
loops keep."""

_BSPLINE = np.array([1.0, 4.0, 1.0]) / 6.0
_PLAIN = np.array([0.0, 1.0, 0.0])


def _stencil(volume: Volume, smooth: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the compiled gradient lookups read: the (Z, Y, X) samples, the weights (3,)
    across the difference's axis (the B-spline's [1, 4, 1] / 6 when `smooth`, else
    [0, 1, 0]: plain central differences) and 1 / (2 h) per axis (x, y, z)."""
    return (volume.data, _BSPLINE if smooth else _PLAIN,
            0.5 / np.asarray(volume.spacing, np.float64))


@numba.njit(**PART)
def gradient_lerp(data: np.ndarray, w: np.ndarray, inverse: np.ndarray, z: float, y: float,
                  x: float, corners: np.ndarray, window: np.ndarray, out: np.ndarray) -> None:
    """out[:] = the gradient at the fractional index (z, y, x): the trilinear interpolation
    (as `_lerp3`, clamped at the border) of the eight surrounding voxels' gradients
    (`_corner_gradients`, into the scratch arrays `corners` and `window`)."""
    nz, ny, nx = data.shape
    z0, _, fz = _axis_weights(z, nz)
    y0, _, fy = _axis_weights(y, ny)
    x0, _, fx = _axis_weights(x, nx)
    _corner_gradients(data, w, inverse, z0, y0, x0, corners, window)
    _lerp_corners(corners, fz, fy, fx, out)


@numba.njit(**PART)
def _corner_gradients(data: np.ndarray, w: np.ndarray, inverse: np.ndarray, z0: int, y0: int,
                      x0: int, corners: np.ndarray, window: np.ndarray) -> None:
    """corners (8, 3) float32 = the gradients (gx, gy, gz) at the corners of the cell
    whose lowest corner is voxel (z0, y0, x0) of the (Z, Y, X) `data`, x fastest: along
    each axis the central difference, along the other two the weights `w` (3,), edge
    samples repeated past the border ("nearest"), times `inverse` (x, y, z).

    The 4 × 4 × 4 samples around the cell, which the eight corners' stencils share, are
    read once into the float32 scratch `window` (exact for every stored type: integers
    would wrap in the differences)."""
    nz, ny, nx = data.shape
    for a in range(4):
        zz = min(max(z0 - 1 + a, 0), nz - 1)
        for b in range(4):
            yy = min(max(y0 - 1 + b, 0), ny - 1)
            for c in range(4):
                window[a, b, c] = np.float32(data[zz, yy, min(max(x0 - 1 + c, 0), nx - 1)])
    k = 0
    for cz in range(2):
        for cy in range(2):
            for cx in range(2):
                gx = 0.0
                gy = 0.0
                gz = 0.0
                for a in range(3):
                    for b in range(3):
                        wab = w[a] * w[b]
                        gx += wab * (window[cz + a, cy + b, cx + 2] - window[cz + a, cy + b, cx])
                        gy += wab * (window[cz + a, cy + 2, cx + b] - window[cz + a, cy, cx + b])
                        gz += wab * (window[cz + 2, cy + a, cx + b] - window[cz, cy + a, cx + b])
                corners[k, 0] = gx * inverse[0]
                corners[k, 1] = gy * inverse[1]
                corners[k, 2] = gz * inverse[2]
                k += 1


@numba.njit(**PART)
def _lerp_corners(corners: np.ndarray, fz: float, fy: float, fx: float, out: np.ndarray
                  ) -> None:
    """out[:] = the trilinear mix of the (8, 3) `corners` (`_corner_gradients`) at the
    weights (fz, fy, fx) of the upper corners."""
    for c in range(3):
        a = (1 - fx) * corners[0, c] + fx * corners[1, c]
        b = (1 - fx) * corners[2, c] + fx * corners[3, c]
        d = (1 - fx) * corners[4, c] + fx * corners[5, c]
        e = (1 - fx) * corners[6, c] + fx * corners[7, c]
        out[c] = (1 - fz) * ((1 - fy) * a + fy * b) + fz * ((1 - fy) * d + fy * e)


@numba.njit(**JIT)
def _gradients(data: np.ndarray, w: np.ndarray, inverse: np.ndarray, index_zyx: np.ndarray,
               out: np.ndarray) -> None:
    """out[i] = the gradient at index_zyx[i] (N, 3) (`gradient_lerp`); NaN where an
    index is NaN."""
    corners = np.empty((8, 3), np.float32)
    window = np.empty((4, 4, 4), np.float32)
    g = np.empty(3)
    for i in range(index_zyx.shape[0]):
        z, y, x = index_zyx[i, 0], index_zyx[i, 1], index_zyx[i, 2]
        if z != z or y != y or x != x:
            out[i, :] = np.nan
        else:
            gradient_lerp(data, w, inverse, z, y, x, corners, window, g)
            out[i, 0], out[i, 1], out[i, 2] = g[0], g[1], g[2]


@numba.njit(**PART)
def _axis_weights(c: float, n: int) -> tuple[int, int, float]:
    """Lower index, upper index and upper weight of fractional index c on an axis of n
    samples, clamped to the edge samples (``map_coordinates(order=1, mode="nearest")``)."""
    c = min(max(c, 0.0), n - 1.0)
    lo = min(int(c), max(n - 2, 0))
    return lo, min(lo + 1, n - 1), c - lo


@numba.njit(**PART)
def _lerp3(grid: np.ndarray, z: float, y: float, x: float, out: np.ndarray) -> None:
    """out[:] = trilinear interpolation of the (Z, Y, X, C) grid at index (z, y, x)."""
    nz, ny, nx, _ = grid.shape
    z0, z1, fz = _axis_weights(z, nz)
    y0, y1, fy = _axis_weights(y, ny)
    x0, x1, fx = _axis_weights(x, nx)
    _lerp_cell(grid, z0, z1, y0, y1, x0, x1, fz, fy, fx, out)


@numba.njit(**PART)
def _lerp_cell(grid: np.ndarray, z0: int, z1: int, y0: int, y1: int, x0: int, x1: int,
               fz: float, fy: float, fx: float, out: np.ndarray) -> None:
    """out[:] = the trilinear mix of the (Z, Y, X, C) grid's cell of corners (z0 … x1) at
    the weights (fz, fy, fx) of the upper corners (`_axis_weights`)."""
    for c in range(grid.shape[3]):
        out[c] = _cell_mix(grid, z0, z1, y0, y1, x0, x1, fz, fy, fx, c)


@numba.njit(**PART)
def _cell_mix(grid: np.ndarray, z0: int, z1: int, y0: int, y1: int, x0: int, x1: int,
              fz: float, fy: float, fx: float, c: int) -> float:
    """Channel c's trilinear mix, float64, of the (Z, Y, X, C) grid's cell of corners
    (z0 … x1) at the weights (fz, fy, fx) of the upper corners."""
    a = (1 - fx) * grid[z0, y0, x0, c] + fx * grid[z0, y0, x1, c]
    b = (1 - fx) * grid[z0, y1, x0, c] + fx * grid[z0, y1, x1, c]
    d = (1 - fx) * grid[z1, y0, x0, c] + fx * grid[z1, y0, x1, c]
    e = (1 - fx) * grid[z1, y1, x0, c] + fx * grid[z1, y1, x1, c]
    return (1 - fz) * ((1 - fy) * a + fy * b) + fz * ((1 - fy) * d + fy * e)


@numba.njit(**JIT)
def _trilinear(grid: np.ndarray, index_zyx: np.ndarray, out: np.ndarray) -> None:
    """out[i] = trilinear interpolation of the (Z, Y, X, C) grid at index_zyx[i] (N, 3);
    NaN where an index is NaN."""
    for i in range(index_zyx.shape[0]):
        z, y, x = index_zyx[i, 0], index_zyx[i, 1], index_zyx[i, 2]
        if z != z or y != y or x != x:
            out[i, :] = np.nan
        else:
            _lerp3(grid, z, y, x, out[i])


@numba.njit(**JIT)
def newton_steps(data: np.ndarray, samples: np.ndarray, w: np.ndarray, inverse: np.ndarray,
                 origin: np.ndarray, spacing: np.ndarray,
                 points: np.ndarray, levels: np.ndarray, max_move: float, iterations: int,
                 out: np.ndarray) -> None:
    """Newton steps p += (level − ρ(p)) ∇ρ / |∇ρ|² from each (N, 3) world point, the
    total move clamped to `max_move`; stops once a step moved less than 1e-4 voxel (Newton
    converges quadratically where the gradient is regular). Steps that stay in one cell of
    the volume, as the last few mostly do, reuse its eight corner gradients, and so do
    steps back into the cell before it (a third of the cells a step enters on a noisy CT:
    steps that overshoot across a cell's face and come back).

    Damped where the field is flat: a step is at most one voxel long, and a point gets
    one more step per voxel of `max_move`, so a point in a plateau next to the surface
    (small gradient: an undamped step would overshoot far past it) walks up to it. Where
    the steps stall (`STALLED_FRACTION`), the nearest crossing of the level along the 26
    neighbour directions is taken instead (`_nearest_crossing`)."""
    value = np.empty(1)
    g = np.empty(3)
    corners = np.empty((2, 8, 3), np.float32)  # of `cell` (at `slot`) and of `before`
    window = np.empty((4, 4, 4), np.float32)
    lines = _neighbour_directions(spacing)  # the stalled points' search lines
    frame = frame_of(origin, spacing)
    ox, oy, oz, hx, hy, hz = frame
    voxel = min(hx, hy, hz)
    tiny = 1e-4 * voxel
    steps = iterations + int(max_move / voxel)
    nz, ny, nx = samples.shape
    cell, before, slot = (-1, -1, -1), (-1, -1, -1), 0  # whose corner gradients are held
    for i in range(points.shape[0]):
        sx, sy, sz = points[i, 0], points[i, 1], points[i, 2]
        px, py, pz = sx, sy, sz
        for _ in range(steps):
            zi, yi, xi = (pz - oz) / hz, (py - oy) / hy, (px - ox) / hx
            z0, z1, fz = _axis_weights(zi, nz)  # once for the value and the gradient
            y0, y1, fy = _axis_weights(yi, ny)
            x0, x1, fx = _axis_weights(xi, nx)
            _lerp_cell(data, z0, z1, y0, y1, x0, x1, fz, fy, fx, value)
            here = (z0, y0, x0)
            if here != cell:
                slot = 1 - slot  # `before`'s corners, or the slot to overwrite
                if here != before:
                    _corner_gradients(samples, w, inverse, z0, y0, x0, corners[slot], window)
                cell, before = here, cell
            _lerp_corners(corners[slot], fz, fy, fx, g)
            g2 = max(g[0] * g[0] + g[1] * g[1] + g[2] * g[2], 1e-30)
            step = (levels[i] - value[0]) / g2
            length = abs(step) * np.sqrt(g2)
            if length > voxel:
                step *= voxel / length
            qx, qy, qz = px + step * g[0], py + step * g[1], pz + step * g[2]
            dx, dy, dz = qx - sx, qy - sy, qz - sz
            dist = np.sqrt(dx * dx + dy * dy + dz * dz)
            if dist > max_move:
                scale = max_move / dist
                qx, qy, qz = sx + dx * scale, sy + dy * scale, sz + dz * scale
            moved = abs(qx - px) + abs(qy - py) + abs(qz - pz)
            px, py, pz = qx, qy, qz
            if moved < tiny:
                break
        start = value_in(data, frame, sx, sy, sz) - levels[i]
        end = value_in(data, frame, px, py, pz) - levels[i]
        if abs(end) > STALLED_FRACTION * abs(start):  # Newton stalled: search the lines
            px, py, pz = _nearest_crossing(data, frame, lines, sx, sy, sz, start, levels[i],
                                           max_move, px, py, pz)
        out[i, 0], out[i, 1], out[i, 2] = px, py, pz


STALLED_FRACTION = 0.1
"""Newton has stalled when the residual |ρ − level| ends above this fraction of where it
started (noisy or sharp-edged data, where the smoothed gradient misleads the steps). At
1 % noisy texels that had all but converged searched too (engine CT plan 24 s instead of
10 s) for the same errors."""


@numba.njit(**PART)
def frame_of(origin: np.ndarray, spacing: np.ndarray) -> tuple[float, ...]:
    """(ox, oy, oz, hx, hy, hz): the (3,) world `origin` and `spacing` (x, y, z) as six
    floats, for compiled loops that look values up many times (`value_in`): the Newton
    steps and their line search (`_nearest_crossing`)."""
    return origin[0], origin[1], origin[2], spacing[0], spacing[1], spacing[2]


@numba.njit(**PART)
def value_in(data: np.ndarray, frame: tuple[float, ...], x: float, y: float, z: float
             ) -> float:
    """Trilinear value, float64, of the (Z, Y, X, 1) `data` at world (x, y, z), clamped
    at the border (``map_coordinates(order=1, mode="nearest")``), in the grid placed by
    `frame` (`frame_of`); NaN coordinates are the caller's to exclude."""
    ox, oy, oz, hx, hy, hz = frame
    nz, ny, nx, _ = data.shape
    z0, z1, fz = _axis_weights((z - oz) / hz, nz)
    y0, y1, fy = _axis_weights((y - oy) / hy, ny)
    x0, x1, fx = _axis_weights((x - ox) / hx, nx)
    return _cell_mix(data, z0, z1, y0, y1, x0, x1, fz, fy, fx, 0)


@numba.njit(**PART)
def value_at_world(data: np.ndarray, origin: np.ndarray, spacing: np.ndarray, x: float,
                   y: float, z: float, scratch: np.ndarray) -> float:
    """`value_in` of the (Z, Y, X, 1) `data` at world (x, y, z), in `scratch`'s type ((1,)
    of `value_at`'s result type): the operations of `value_at`, for compiled callers."""
    scratch[0] = value_in(data, frame_of(origin, spacing), x, y, z)
    return scratch[0]


@numba.njit(**JIT)
def _nearest_crossing(data: np.ndarray, frame: tuple[float, ...], lines: np.ndarray,
                      sx: float, sy: float, sz: float, start: float, level: float,
                      max_move: float, fx: float, fy: float, fz: float):
    """The nearest point within `max_move` of (sx, sy, sz) — where ρ − `level` is
    `start` — at which the trilinear field (`value_in` in `frame`) crosses `level` along
    one of the (26, 3) unit `lines` to the neighbouring voxels' directions
    (`_neighbour_directions`; steps of half a voxel, then bisection); (fx, fy, fz) when
    none crosses. A texel is a corner of a cell its target surface crosses, so along some
    such line the level lies within a cell's diagonal, whatever the gradient says.

    The lines are stepped together, a half voxel at a time: the first step at which some
    line changes sign is bisected on the first such line (in the order of `lines`), and
    no line is stepped further."""
    step = 0.5 * min(frame[3], frame[4], frame[5])
    near, t = 0.0, step
    while t <= max_move:
        for a in range(lines.shape[0]):
            dx, dy, dz = lines[a, 0], lines[a, 1], lines[a, 2]
            v = value_in(data, frame, sx + t * dx, sy + t * dy, sz + t * dz) - level
            if v * start <= 0:
                far = t
                for _ in range(24):
                    mid = 0.5 * (near + far)
                    w = value_in(data, frame, sx + mid * dx, sy + mid * dy,
                                 sz + mid * dz) - level
                    if w * start <= 0:
                        far = mid
                    else:
                        near = mid
                return sx + far * dx, sy + far * dy, sz + far * dz
        near, t = t, t + step
    return fx, fy, fz


@numba.njit(**JIT)
def _neighbour_directions(spacing: np.ndarray) -> np.ndarray:
    """(26, 3) unit world directions (x, y, z) from a voxel to its 26 neighbours of the
    grid of `spacing` (x, y, z), x fastest, then y, then z."""
    lines = np.empty((26, 3))
    k = 0
    for a in range(27):
        if a == 13:  # (0, 0, 0)
            continue
        dx, dy, dz = (a % 3 - 1) * spacing[0], (a // 3 % 3 - 1) * spacing[1], \
            (a // 9 - 1) * spacing[2]
        norm = np.sqrt(dx * dx + dy * dy + dz * dz)
        lines[k, 0], lines[k, 1], lines[k, 2] = dx / norm, dy / norm, dz / norm
        k += 1
    return lines


def newton_to_level(volume: Volume, points_xyz: np.ndarray, levels: float | np.ndarray,
                    max_move: float, iterations: int = 4, smooth: bool = True) -> np.ndarray:
    """(N, 3) world points moved onto ρ = levels (N,) by Newton steps along the gradient
    (smoothed unless not `smooth`), the total move clamped to `max_move` world units.

    One compiled pass per point (value and gradient read together, no temporaries, no
    GIL): the bake does this for every texel on each of its levels, large batches on
    threads (`cores.for_ranges`)."""
    points = np.ascontiguousarray(points_xyz, np.float64).reshape(-1, 3)
    levels = np.ascontiguousarray(np.broadcast_to(levels, (len(points),)), np.float64)
    out = np.empty_like(points)
    fixed = (volume.data[..., None], *normal_stencil(volume, smooth))

    def steps(lo: int, hi: int) -> None:
        newton_steps(*fixed, points[lo:hi], levels[lo:hi], float(max_move), int(iterations),
                     out[lo:hi])

    cores.for_ranges(steps, len(points), 1, "newton")
    return out


@numba.njit(**JIT)
def _grid_trilinear(data: np.ndarray, iz: np.ndarray, iy: np.ndarray, ix: np.ndarray,
                    out: np.ndarray) -> None:
    """out[k, j, i] = trilinear interpolation of the (Z, Y, X, 1) `data` at the fractional
    index (iz[k], iy[j], ix[i]) — `_lerp3` at every point of the grid, no temporaries."""
    value = np.empty(1)
    for k in range(iz.shape[0]):
        for j in range(iy.shape[0]):
            for i in range(ix.shape[0]):
                _lerp3(data, iz[k], iy[j], ix[i], value)
                out[k, j, i] = value[0]


def values_on_grid(volume: Volume, x: np.ndarray, y: np.ndarray, z: np.ndarray
                   ) -> np.ndarray:
    """(len(z), len(y), len(x)) float32 trilinear field values at the points of the world
    grid spanned by the coordinates `x`, `y`, `z` (each 1-D, world units): bit for bit
    `value_at` at those points, one compiled pass (z-slabs on threads: `cores.for_ranges`)."""
    axes = [(np.asarray(c, np.float64) - o) / h
            for c, o, h in zip((x, y, z), volume.origin, volume.spacing, strict=True)]
    out = np.empty((len(axes[2]), len(axes[1]), len(axes[0])), np.float32)

    def slab(lo: int, hi: int) -> None:
        _grid_trilinear(volume.data[..., None], axes[2][lo:hi], axes[1], axes[0], out[lo:hi])

    cores.for_ranges(slab, len(axes[2]), out[0].size if len(out) else 1, "grid values")
    return out


@numba.njit(**JIT)
def along_normals(data: np.ndarray, samples: np.ndarray, w: np.ndarray,
                  inverse: np.ndarray, origin: np.ndarray, spacing: np.ndarray,
                  points: np.ndarray, distance: float, sign: float, out: np.ndarray) -> None:
    """out[i] = trilinear value at points[i] + distance · n, n = sign · ∇ρ/|∇ρ| there (sign
    −1: `normals_from_gradient`'s normals, +1 flipped; (0, 0, −sign) where ∇ρ = 0)."""
    g = np.empty(3)
    value = np.empty(1)
    corners = np.empty((8, 3), np.float32)
    window = np.empty((4, 4, 4), np.float32)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        gradient_lerp(samples, w, inverse, (z - origin[2]) / spacing[2],
                       (y - origin[1]) / spacing[1], (x - origin[0]) / spacing[0], corners,
                       window, g)
        norm = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        if norm > 0:
            x += distance * sign * g[0] / norm
            y += distance * sign * g[1] / norm
            z += distance * sign * g[2] / norm
        else:
            z -= distance * sign
        out[i] = value_at_world(data, origin, spacing, x, y, z, value)


def values_along_normals(volume: Volume, points_xyz: np.ndarray, distance: float,
                         smooth: bool = True, flip: bool = False) -> np.ndarray:
    """(N,) trilinear field values at the (N, 3) world points moved `distance` world units
    along their unit normals (`normals_at`: high → low values unless `flip`), in one
    compiled pass on threads — where a path starting there would begin."""
    points = np.ascontiguousarray(points_xyz, np.float64).reshape(-1, 3)
    out = np.empty(len(points))
    fixed = (volume.data[..., None], *normal_stencil(volume, smooth))

    def part(lo: int, hi: int) -> None:
        along_normals(*fixed, points[lo:hi], float(distance), 1.0 if flip else -1.0,
                      out[lo:hi])

    cores.for_ranges(part, len(points), 1, "along normals")
    return out


def _interpolate(grid: np.ndarray, index_zyx: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a (Z, Y, X[, C]) grid at (N, 3) fractional indices,
    clamped at the border: (N[, C]) in the grid's float type (float32 for integer
    samples). A compiled loop: the same result as ``scipy.ndimage.map_coordinates(
    order=1, mode="nearest")``, an order of magnitude faster, and without the GIL (bake
    workers keep tracing meanwhile)."""
    scalar = grid.ndim == 3
    cube = grid[..., None] if scalar else grid
    index = np.ascontiguousarray(index_zyx, np.float64).reshape(-1, 3)
    out = np.empty((len(index), cube.shape[-1]), np.result_type(grid.dtype, np.float32))
    _trilinear(cube, index, out)
    return out[:, 0] if scalar else out


def value_at(volume: Volume, points_xyz: np.ndarray) -> np.ndarray:
    """(N,) trilinear field values at (N, 3) world points (clamped at the border)."""
    return _interpolate(volume.data, volume.world_to_index(points_xyz))


def gradient_at(volume: Volume, points_xyz: np.ndarray, smooth: bool = True) -> np.ndarray:
    """(N, 3) float32 gradient at (N, 3) world points, value per world unit (clamped at
    the border; NaN at NaN points), in one compiled pass on threads."""
    index = np.ascontiguousarray(volume.world_to_index(points_xyz), np.float64).reshape(-1, 3)
    out = np.empty((len(index), 3), np.float32)
    fixed = _stencil(volume, smooth)

    def part(lo: int, hi: int) -> None:
        _gradients(*fixed, index[lo:hi], out[lo:hi])

    cores.for_ranges(part, len(index), 8, "gradients")
    return out


def normals_from_gradient(grad: np.ndarray, flip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``-g/|g|`` from (N, 3) gradients.

    Returns:
        normals: (N, 3) float32; (0, 0, 1) where the gradient vanishes.
        magnitude: (N,) |g|, value per world unit.
    """
    mag = np.linalg.norm(grad, axis=-1)
    safe = np.where(mag > 0, mag, 1.0)
    n = -grad / safe[:, None]
    n[mag == 0] = (0.0, 0.0, 1.0)
    if flip:
        n = -n
    return n.astype(np.float32), mag


def normals_at(
    volume: Volume, points_xyz: np.ndarray, smooth: bool = True, flip: bool = False
) -> np.ndarray:
    """(N, 3) float32 unit normals (high → low values, low → high if `flip`) at (N, 3)
    world points: ``normals_from_gradient(gradient_at(...), flip)[0]``, to the bit, in one
    compiled pass on threads (`normal_in`)."""
    points = np.ascontiguousarray(points_xyz, np.float64).reshape(-1, 3)
    out = np.empty((len(points), 3), np.float32)
    fixed = normal_stencil(volume, smooth)

    def part(lo: int, hi: int) -> None:
        _normals(*fixed, points[lo:hi], bool(flip), out[lo:hi])

    cores.for_ranges(part, len(points), 8, "normals")
    return out


def normal_stencil(volume: Volume, smooth: bool = True) -> tuple[np.ndarray, ...]:
    """What `normal_in` reads of `volume`: ``(data, w, inverse, origin, spacing)``."""
    return (*_stencil(volume, smooth), np.asarray(volume.origin, np.float64),
            np.asarray(volume.spacing, np.float64))


@numba.njit(**PART)
def normal_in(data: np.ndarray, w: np.ndarray, inverse: np.ndarray, origin: np.ndarray,
              spacing: np.ndarray, x: float, y: float, z: float, flip: bool,
              scratch: tuple[np.ndarray, np.ndarray, np.ndarray]
              ) -> tuple[np.float32, np.float32, np.float32]:
    """(nx, ny, nz) float32: `normals_at`'s normal at world (x, y, z) (`_stencil`'s
    `data`, `w`, `inverse`; (3,) float64 `origin`, `spacing`): the gradient
    (`gradient_lerp`) as float32, over its float32 length — ``-g/|g|``, (0, 0, 1) where it
    vanishes, NaN at NaN — the float32 operations of `normals_from_gradient`, negated if
    `flip`. `scratch`: `normal_scratch()`, one per thread."""
    iz, iy, ix = (z - origin[2]) / spacing[2], (y - origin[1]) / spacing[1], \
        (x - origin[0]) / spacing[0]
    corners, window, g = scratch
    if iz != iz or iy != iy or ix != ix:  # `gradient_at`'s NaN gradient
        g[0] = g[1] = g[2] = np.nan
    else:
        gradient_lerp(data, w, inverse, iz, iy, ix, corners, window, g)
    gx, gy, gz = np.float32(g[0]), np.float32(g[1]), np.float32(g[2])
    mag = np.sqrt(gx * gx + gy * gy + gz * gz)  # numpy's float32 norm: (x² + y²) + z²
    if mag == 0:
        nx, ny, nz = np.float32(0.0), np.float32(0.0), np.float32(1.0)
    else:
        safe = mag if mag > 0 else np.float32(1.0)  # NaN: numpy divides by 1
        nx, ny, nz = -gx / safe, -gy / safe, -gz / safe
    if flip:
        nx, ny, nz = -nx, -ny, -nz
    return nx, ny, nz


@numba.njit(**JIT)
def normal_scratch() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scratch arrays of one thread's `normal_in` calls."""
    return (np.empty((8, 3), np.float32), np.empty((4, 4, 4), np.float32), np.empty(3))


@numba.njit(**JIT)
def _normals(data: np.ndarray, w: np.ndarray, inverse: np.ndarray, origin: np.ndarray,
             spacing: np.ndarray, points: np.ndarray, flip: bool, out: np.ndarray) -> None:
    """out[i] = `normal_in` at the (N, 3) world `points`[i]."""
    scratch = normal_scratch()
    for i in range(points.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = normal_in(
            data, w, inverse, origin, spacing, points[i, 0], points[i, 1], points[i, 2], flip,
            scratch)
