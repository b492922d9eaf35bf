"""The compiled kernels of a bake to a texel error (`baking.density`, `baking.fills`): a
half lattice's nodes around texels (`corner_nodes`) and at a half index (`node_at`), the
surpluses of node pairs that judge a brick (`node_pair_surpluses`) and texel luminance
summed in a fixed order (`weighted_sums`) — each a block of texels per call, without the
GIL, with the array code's bits.
"""

from __future__ import annotations

import numba
import numpy as np

from isolume.baking import octahedral
from isolume.volumes.field import JIT


@numba.njit(**JIT)
def corner_nodes(node_rows: np.ndarray, coords: np.ndarray, offset: int, stride: int,
                 shape: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> None:
    """`fills.Nodes.corners` into (N, 8) `rows` and `weights`, from a half lattice's
    `node_rows` map (`fills.Nodes.rows`) at `offset`; `shape`: (3,) the lattice's texels."""
    half = np.empty(3, np.int64)
    for n in range(len(coords)):
        for k in range(8):
            weight = 1.0
            inside = True
            for axis in range(3):
                c = np.int64(coords[n, axis]) - offset
                low = c - (c % stride + stride) % stride
                frac = (c - low) / stride
                step = (k >> (2 - axis)) & 1
                weight *= frac if step == 1 else 1.0 - frac
                at = low + stride * step
                inside &= at >= 0 and at + offset < shape[axis]
                half[axis] = at // 2
            row = node_rows[half[0], half[1], half[2]] if inside and weight > 0 else -1
            rows[n, k] = row
            weights[n, k] = weight if row >= 0 else 0.0


@numba.njit(**JIT)
def node_pair_surpluses(node_rows: np.ndarray, half: np.ndarray, at: np.ndarray,
                        directions: np.ndarray, luminance: np.ndarray, error: np.ndarray,
                        shown: np.ndarray, facing: np.ndarray, floor: float, power: int,
                        surplus: np.ndarray, noise: np.ndarray) -> None:
    """`density.pair_surpluses` into (N, K) `surplus` and `noise` (set where a pair is found), for
    the nodes at plan positions (N,) `at` and (N, 3) half indices `half`, along (K, 3)
    `directions`, from a half lattice's `node_rows` map (`fills.Nodes.rows`)."""
    pair = np.empty(2, np.int64)
    for i in range(len(at)):
        cx, cy = facing[at[i], 0], facing[at[i], 1]
        known = cx != 0 or cy != 0
        nx, ny, nz = octahedral.decode_pair(int(cx), int(cy))
        for k in range(len(directions)):
            found = True
            for s in range(2):
                step = 2 * s - 1
                row = node_at(node_rows, half[i, 0] + step * directions[k, 0],
                              half[i, 1] + step * directions[k, 1],
                              half[i, 2] + step * directions[k, 2])
                found &= row >= 0 and shown[row] and (not known or octahedral.side_of(
                    facing[row, 0], facing[row, 1], nx, ny, nz, power) >= floor)
                pair[s] = row
            if found:
                low, high = pair[0], pair[1]
                surplus[i, k] = luminance[at[i]] - 0.5 * (luminance[low] + luminance[high])
                noise[i, k] = error[at[i]] + 0.25 * (error[low] + error[high])


@numba.njit(**JIT)
def node_at(node_rows: np.ndarray, z: int, y: int, x: int) -> int:
    """The plan position of the node at half index (z, y, x) of a half lattice's
    `node_rows` map (`fills.Nodes.rows`); −1 where none is, or outside the map."""
    shape = node_rows.shape
    if 0 <= z < shape[0] and 0 <= y < shape[1] and 0 <= x < shape[2]:
        return node_rows[z, y, x]
    return -1


@numba.njit(**JIT)
def weighted_sums(values: np.ndarray, weights: np.ndarray, out: np.ndarray) -> None:
    """out[t] = Σ_c values[t, c] · weights[c], c in order, for (T, C) `values` (C ≥ 1),
    in the type of their products."""
    for t in range(values.shape[0]):
        total = values[t, 0] * weights[0]
        for c in range(1, values.shape[1]):
            total += values[t, c] * weights[c]
        out[t] = total
