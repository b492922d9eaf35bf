"""Unit vectors in two bytes: octahedral encoding (Meyer et al. 2010; Cigolle et al. 2014).

A unit vector n maps to p = (n_x, n_y) / (|n_x| + |n_y| + |n_z|) on the octahedron's upper
half, the lower half folded over the square's corners, so p covers [-1, 1]²; each
coordinate is stored as a byte b ≈ (p + 1) / 2 · 255 (rounded up or down, whichever pair
decodes nearest n) — what a GL RG8 (UNORM) texture reads back as b / 255. Round trip: at
most 0.63° of angular error, mean 0.31° (measured over a million random directions;
`tests/test_facing.py`).

The code (0, 0) is reserved: `UNKNOWN`, no direction (a texel not computed yet, or a
lattice file written before facings were kept). The square's corner (0, 0) is the
direction −z, as are the other three corners, so −z is stored as (255, 255) instead. A
zero-length or non-finite vector encodes to `UNKNOWN`; `decode` gives (0, 0, 0) for it.
``shaders/gbuffer.glsl`` decodes the same bytes (`from_octahedral`, used by
``shaders/lattice.glsl``'s `side_weight`).
"""

from __future__ import annotations

import numba
import numpy as np

UNKNOWN = (0, 0)
"""The code of no direction."""
STEPS = 255.0


def encode(vectors: np.ndarray) -> np.ndarray:
    """(..., 2) uint8 codes of (..., 3) vectors (any length; zero or non-finite ones get
    `UNKNOWN`): of the four codes around the vector's octahedral point, the one whose
    direction lies nearest it (rounding each coordinate alone errs up to 0.9°). One
    compiled pass (`_encode_rows`), each candidate's direction as `decode` makes it."""
    v = np.asarray(vectors, np.float64)
    rows = np.ascontiguousarray(v.reshape(-1, 3))
    out = np.empty((len(rows), 2), np.uint8)
    _encode_rows(rows, out)
    return out.reshape(*v.shape[:-1], 2)


@numba.njit(nogil=True, cache=True)
def _encode_rows(vectors: np.ndarray, out: np.ndarray) -> None:
    """out[i] = `encode`'s code (2,) uint8 of vectors[i] (N, 3) float64."""
    for i in range(vectors.shape[0]):
        x, y, z = vectors[i, 0], vectors[i, 1], vectors[i, 2]
        l1 = abs(x) + abs(y) + abs(z)
        if not (np.isfinite(l1) and l1 > 1e-12):
            out[i, 0], out[i, 1] = 0, 0
            continue
        ux, uy, uz = x / l1, y / l1, z / l1
        px, py = ux, uy
        if uz < 0:
            px, py = _fold_pair(ux, uy)
        bx = np.floor((min(max(px, -1.0), 1.0) + 1) * (STEPS / 2))
        by = np.floor((min(max(py, -1.0), 1.0) + 1) * (STEPS / 2))
        best_x, best_y, best_cos = 0, 0, -np.inf
        for step in range(4):
            cx = int(min(max(bx + step // 2, 0.0), STEPS))
            cy = int(min(max(by + step % 2, 0.0), STEPS))
            dx, dy, dz = decode_pair(cx, cy)
            cos = dx * ux + dy * uy + dz * uz
            if step == 0 or cos > best_cos:
                best_x, best_y, best_cos = cx, cy, cos
        if best_x == 0 and best_y == 0:  # -z: a corner that is not UNKNOWN
            best_x, best_y = 255, 255
        out[i, 0], out[i, 1] = best_x, best_y


@numba.njit(nogil=True, cache=True)
def decode_pair(cx: int, cy: int) -> tuple[float, float, float]:
    """The unit vector of the code (cx, cy), `UNKNOWN` read as the corner −z."""
    px, py = cx / STEPS * 2 - 1, cy / STEPS * 2 - 1
    z = 1 - (abs(px) + abs(py))
    if z < 0:
        px, py = _fold_pair(px, py)
    norm = np.sqrt(px * px + py * py + z * z)
    return px / norm, py / norm, z / norm


@numba.njit(nogil=True, cache=True)
def _fold_pair(px: float, py: float) -> tuple[float, float]:
    """The octahedral square's fold of the point (px, py) (its own inverse): the lower
    half's points to the corners and back."""
    return ((1 - abs(py)) * (1.0 if px >= 0 else -1.0),
            (1 - abs(px)) * (1.0 if py >= 0 else -1.0))


def decode(codes: np.ndarray) -> np.ndarray:
    """(..., 3) float64 unit vectors of (..., 2) uint8 codes ((0, 0, 0) for `UNKNOWN`),
    in one compiled pass (`_decode_rows`)."""
    c = np.asarray(codes)
    rows = np.ascontiguousarray(c.reshape(-1, 2))
    out = np.empty((len(rows), 3))
    _decode_rows(rows, out)
    return out.reshape(*c.shape[:-1], 3)


@numba.njit(nogil=True, cache=True)
def _decode_rows(codes: np.ndarray, out: np.ndarray) -> None:
    """out[i] = `decode`'s (3,) vector of codes[i] (N, 2)."""
    for i in range(codes.shape[0]):
        cx, cy = int(codes[i, 0]), int(codes[i, 1])
        if cx == 0 and cy == 0:
            out[i, 0], out[i, 1], out[i, 2] = 0.0, 0.0, 0.0
        else:
            out[i, 0], out[i, 1], out[i, 2] = decode_pair(cx, cy)


def side_rows(rows: np.ndarray, codes: np.ndarray, normals: np.ndarray,
              power: int) -> np.ndarray:
    """(N, K) max(0, n·m)^`power` for the directions m of the (T, 2) `codes` at (N, K)
    rows `rows` (−1 read as row 0) and the points' (N, 3) unit `normals` n; 1 where a
    code is `UNKNOWN`. In one compiled pass without the GIL (`_side_rows`): for the
    square, the bits of `baking.sided.side_weights` (the dot product summed in numpy's
    `einsum` order); other powers through `pow`, to within rounding."""
    out = np.empty(rows.shape)
    _side_rows(np.ascontiguousarray(rows), np.ascontiguousarray(codes),
               np.ascontiguousarray(normals, np.float64), power, out)
    return out


@numba.njit(nogil=True, cache=True)
def _side_rows(rows: np.ndarray, codes: np.ndarray, normals: np.ndarray, power: int,
               out: np.ndarray) -> None:
    """out[i, k] = `side_rows`'s weight of rows[i, k] (N, K) for normals[i]."""
    for i in range(rows.shape[0]):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        for k in range(rows.shape[1]):
            row = max(rows[i, k], 0)
            out[i, k] = side_of(codes[row, 0], codes[row, 1], nx, ny, nz, power)


@numba.njit(nogil=True, cache=True)
def side_of(cx: int, cy: int, nx: float, ny: float, nz: float, power: int) -> float:
    """max(0, n·m)^`power` of the code (cx, cy)'s direction m and the unit normal (nx, ny,
    nz): `side_rows`' weight of one texel (1 for `UNKNOWN`)."""
    if cx == 0 and cy == 0:
        return 1.0
    dx, dy, dz = decode_pair(int(cx), int(cy))
    cos = max((dx * nx + dz * nz) + dy * ny, 0.0)  # numpy's einsum's order
    return cos * cos if power == 2 else cos ** float(power)


def known(codes: np.ndarray) -> np.ndarray:
    """(...) bool: which of the (..., 2) codes hold a direction (not `UNKNOWN`)."""
    return np.asarray(codes).any(axis=-1)
