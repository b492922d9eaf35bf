"""Compiled random numbers and the single-precision helpers of direction sampling, shared by
the path kernels (`baking.kernels`) and the sky's (`baking.sky_kernels`).

They mirror, and are tested against, the numpy reference functions: `pcg_hash`, `uniform`
and `uniform2` against `baking.rng` (bit for bit), `tangent_frame` against
`baking.sampling.orthonormal_basis`.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from isolume.volumes.field import JIT

_Real = float | np.floating[Any]
"""A scalar as the kernels see it: a Python float or a numpy one (float32 in the loops)."""

_MULT = np.uint32(747796405)
_INC = np.uint32(2891336453)
_M2 = np.uint32(277803737)
GOLDEN = np.uint32(0x9E3779B9)
"""2³²/φ: the step between the keys of consecutive samples and of random dimensions."""
_INV_2_32 = 1.0 / 4294967296.0


@numba.njit(**JIT)
def pcg_hash(x: np.uint32) -> np.uint32:
    """PCG-RXS-M-XS hash of a 32-bit word (`baking.rng.pcg_hash`).

    numba widens integer arithmetic to 64 bits; truncating every product and sum back to
    32 bits lets LLVM keep the hash in 32-bit lanes, eight to a vector register (the
    64-bit form, masked, vectorised four wide with emulated multiplies: 2.7× slower).
    """
    state = np.uint32(x * _MULT + _INC)
    shift = np.uint32((state >> np.uint32(28)) + np.uint32(4))
    word = np.uint32(np.uint32((state >> shift) ^ state) * _M2)
    return np.uint32((word >> np.uint32(22)) ^ word)


@numba.njit(**JIT)
def dimension_key(dim: int) -> np.uint32:
    """The hash that selects random dimension `dim` (`baking.rng.uniform`)."""
    return pcg_hash(np.uint32(np.uint32(dim) + GOLDEN))


@numba.njit(**JIT)
def uniform(key: np.uint32, dim_key: np.uint32) -> float:
    """The uniform in [0, 1) of a path key and a dimension key (`baking.rng.uniform`)."""
    return float(pcg_hash(np.uint32(key ^ dim_key))) * _INV_2_32


@numba.njit(**JIT)
def _top31(key: np.uint32, dim_key: np.uint32) -> np.int32:
    """The hash's top 31 bits as a signed 32-bit integer: it converts to floating point
    in vector lanes (an unsigned 64-bit one does not)."""
    return np.int32(pcg_hash(np.uint32(key ^ dim_key)) >> np.uint32(1))


@numba.njit(**JIT)
def uniform31(key: np.uint32, dim_key: np.uint32) -> float:
    """`uniform` from the hash's top 31 bits, within 2^-32 of `uniform`."""
    return float(_top31(key, dim_key)) * 2.0**-31


@numba.njit(**JIT)
def uniform_f32(key: np.uint32, dim_key: np.uint32) -> np.float32:
    """`uniform31` in single precision, strictly below 1 (`word_uniform_f32` of the
    hash)."""
    return word_uniform_f32(pcg_hash(np.uint32(key ^ dim_key)))


@numba.njit(**JIT)
def word_uniform_f32(word: np.uint32) -> np.float32:
    """A 32-bit word as a float32 uniform in [0, 1): its top 31 bits as a signed integer
    (which converts in vector lanes), times 2⁻³¹, clamped to the largest float32 below 1
    where rounding would reach 1. Converted to float32 directly: one rounding of the same
    exact value as through float64."""
    return min(np.float32(np.int32(word >> np.uint32(1))) * np.float32(2.0**-31),
               np.float32(1.0 - 2.0**-24))


@numba.njit(**JIT)
def net_words(index: int) -> tuple[np.uint32, np.uint32]:
    """Point `index` (≥ 0) of the (0, 2)-sequence in base 2 as two 32-bit words: the van der
    Corput radical inverse and Sobol's second coordinate (generator columns c₀ = 2³¹,
    cₖ = cₖ₋₁ ⊕ cₖ₋₁/2). Every 2ᵐ consecutive points from a multiple of 2ᵐ put one point
    in each of the 2ᵐ elementary boxes of every shape 2⁻ᵃ × 2⁻⁽ᵐ⁻ᵃ⁾ (a (0, m, 2)-net), and
    so do their bits XOR-ed with any two fixed words (a random digital shift: then each
    point alone is uniform)."""
    first = np.uint32(0)
    second = np.uint32(0)
    column = np.uint32(1 << 31)
    bit = np.uint32(1 << 31)
    rest = np.uint32(index)
    while rest:
        if rest & np.uint32(1):
            first = np.uint32(first ^ bit)
            second = np.uint32(second ^ column)
        rest = np.uint32(rest >> np.uint32(1))
        bit = np.uint32(bit >> np.uint32(1))
        column = np.uint32(column ^ (column >> np.uint32(1)))
    return first, second


@numba.njit(**JIT)
def uniform2(keys: np.ndarray, dim: int) -> np.ndarray:
    """(N, 2) float64 uniforms of dimensions `dim`, `dim + 1` (`baking.rng.uniform2`)."""
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    out = np.empty((len(keys), 2))
    for i in range(len(keys)):
        out[i, 0] = uniform(keys[i], k0)
        out[i, 1] = uniform(keys[i], k1)
    return out


@numba.njit(**JIT)
def tangent_frame(nx: _Real, ny: _Real, nz: _Real
                  ) -> tuple[_Real, _Real, _Real, _Real, _Real, _Real]:
    """Tangents (tx, ty, tz), (bx, by, bz) completing the unit normal n to a right-handed
    frame (Duff et al. 2017, branchless; `baking.sampling.orthonormal_basis`), in the
    precision of n (float32 normals stay float32 inside vectorised loops)."""
    one = np.float32(1.0)
    sign = one if nz >= 0 else -one
    a = -one / (sign + nz)
    b = nx * ny * a
    return one + sign * nx * nx * a, sign * b, -sign * nx, b, sign + ny * ny * a, -ny


@numba.njit(**JIT)
def sincos_turns(u: _Real) -> tuple[_Real, _Real]:
    """(cos 2πu, sin 2πu) for float32 u in [0, 1), in float32 to ~1e-7.

    The angle is cut into quarter turns, each rotated about its middle (|x| ≤ π/4), where
    Taylor series to x⁹ (sine) and x⁸ (cosine) are exact to 2e-9 and 3e-8; four times
    cheaper than the libm calls, which would be most of a cosine-sampled direction's cost.
    """
    quarter = np.float32(4.0) * u
    q = np.floor(quarter)  # the quarter, 0 … 3, kept in floating point: integer
    # conversions leave vector lanes (numba widens them to 64 bits, which AVX2 lacks)
    x = (quarter - q - np.float32(0.5)) * np.float32(0.5 * math.pi)
    x2 = x * x
    s = x * (np.float32(1.0) + x2 * (np.float32(-1.0 / 6) + x2 * (np.float32(1.0 / 120) + x2 * (
        np.float32(-1.0 / 5040) + x2 * np.float32(1.0 / 362880)))))
    c = np.float32(1.0) + x2 * (np.float32(-0.5) + x2 * (np.float32(1.0 / 24) + x2 * (
        np.float32(-1.0 / 720) + x2 * np.float32(1.0 / 40320))))
    half = np.float32(math.sqrt(0.5))  # the quarter's middle, π/4: cos = sin = √½
    cq, sq = half * (c - s), half * (c + s)  # cos, sin of the angle within the quarter
    # turned by q quarters without branches (they mispredict: q is random): odd quarters
    # swap the pair, the second half-turn negates it
    half_turns = np.floor(np.float32(0.5) * q)
    odd = q - np.float32(2.0) * half_turns
    sign = np.float32(1.0) - np.float32(2.0) * half_turns
    return sign * (cq - odd * (sq + cq)), sign * (sq + odd * (cq - sq))
