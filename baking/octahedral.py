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

import numpy as np

UNKNOWN = (0, 0)
"""The code of no direction."""
STEPS = 255.0


def encode(vectors: np.ndarray) -> np.ndarray:
    """(..., 2) uint8 codes of (..., 3) vectors (any length; zero or non-finite ones get
    `UNKNOWN`): of the four codes around the vector's octahedral point, the one whose
    direction lies nearest it (rounding each coordinate alone errs up to 0.9°)."""
    v = np.asarray(vectors, np.float64)
    l1 = np.abs(v).sum(axis=-1, keepdims=True)
    known_ = np.isfinite(l1) & (l1 > 1e-12)
    unit = np.where(known_, v, 0.0) / np.where(known_, l1, 1.0)
    p = np.where(unit[..., 2:3] < 0, _fold(unit[..., :2]), unit[..., :2])
    base = np.floor((np.clip(p, -1, 1) + 1) * (STEPS / 2))
    best, best_cos = None, None
    for step in ((0, 0), (0, 1), (1, 0), (1, 1)):
        codes = np.clip(base + step, 0, STEPS).astype(np.uint8)
        cos = (_decode(codes) * unit).sum(axis=-1)
        if best is None:
            best, best_cos = codes, cos
        else:
            nearer = cos > best_cos
            best = np.where(nearer[..., None], codes, best)
            best_cos = np.where(nearer, cos, best_cos)
    corner = (best == 0).all(axis=-1, keepdims=True)
    best = np.where(corner, np.uint8(255), best)  # -z: a corner that is not UNKNOWN
    return np.where(known_, best, np.uint8(0)).astype(np.uint8)


def decode(codes: np.ndarray) -> np.ndarray:
    """(..., 3) float64 unit vectors of (..., 2) uint8 codes ((0, 0, 0) for `UNKNOWN`)."""
    c = np.asarray(codes)
    return np.where(known(c)[..., None], _decode(c), 0.0)


def _decode(codes: np.ndarray) -> np.ndarray:
    """(..., 3) unit vectors of (..., 2) codes, `UNKNOWN` read as the corner −z."""
    p = np.asarray(codes).astype(np.float64) / STEPS * 2 - 1
    z = 1 - np.abs(p).sum(axis=-1, keepdims=True)
    v = np.concatenate([np.where(z < 0, _fold(p), p), z], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _fold(p: np.ndarray) -> np.ndarray:
    """(..., 2) the octahedral square's fold of (..., 2) points (its own inverse): the
    lower half's points to the corners and back."""
    return (1 - np.abs(p[..., ::-1])) * np.where(p >= 0, 1.0, -1.0)


def known(codes: np.ndarray) -> np.ndarray:
    """(...) bool: which of the (..., 2) codes hold a direction (not `UNKNOWN`)."""
    return np.asarray(codes).any(axis=-1)
