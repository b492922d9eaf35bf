"""Counter-based random numbers: every uniform is a hash of (seed, texel, sample, dimension).

A sample's random numbers depend only on its coordinates, never on how the work was split
into chunks, threads or passes; so the same seed gives the same lattice with any number of
workers, and a resumed bake equals an uninterrupted one. The hash is the PCG-RXS-M-XS
output permutation on 32-bit words (O'Neill 2014), chained over the coordinates.
"""

from __future__ import annotations

import numpy as np

_MULT = np.uint32(747796405)
_INC = np.uint32(2891336453)
_M2 = np.uint32(277803737)
_GOLDEN = np.uint32(0x9E3779B9)
_INV_2_32 = 1.0 / 4294967296.0


def pcg_hash(x: np.ndarray) -> np.ndarray:
    """PCG-RXS-M-XS hash of a uint32 array (same shape, uint32)."""
    with np.errstate(over="ignore"):
        state = x * _MULT + _INC
        word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * _M2
        return (word >> np.uint32(22)) ^ word


def path_keys(seed: int, texels: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(N,) uint32 keys of the paths (seed, texel id, sample index).

    Args:
        texels: (N,) integer texel ids (flat lattice index).
        samples: (N,) integer sample index within the texel.
    """
    with np.errstate(over="ignore"):
        h = pcg_hash(texels.astype(np.uint32) ^ np.uint32(seed_key(seed)))
        return pcg_hash(h + samples.astype(np.uint32) * _GOLDEN)


def seed_key(seed: int) -> int:
    """The hash of the low 32 bits of `seed` that every path key of a bake starts from."""
    return int(pcg_hash(np.full(1, seed & 0xFFFFFFFF, np.uint32))[0])


def uniform(keys: np.ndarray, dim: int) -> np.ndarray:
    """(N,) float64 uniforms in [0, 1) for dimension `dim` of the paths `keys`."""
    with np.errstate(over="ignore"):
        h = pcg_hash(keys ^ pcg_hash(np.full(1, np.uint32(dim) + _GOLDEN, np.uint32)))
    return h.astype(np.float64) * _INV_2_32


def uniform2(keys: np.ndarray, dim: int) -> np.ndarray:
    """(N, 2) uniforms for dimensions `dim` and `dim + 1`."""
    return np.stack([uniform(keys, dim), uniform(keys, dim + 1)], axis=1)
