"""Checks of a bake's fill (`baking.density`): a fill that leans to one side
(`drift_error`), and filled texels checked against the traced texels beside them
(`stray_fills`), before the fill is made.

A bake to a texel error traces, besides its nodes, the texels of its fine bricks and those
no half lattice can fill: *witnesses*, whose light the nodes did not decide. At each, the
half lattice's side-aware mix of its nodes' light (what a fill would give it) less its
traced light is a *residual*: what the fill gets wrong there, measured. A texel to be
filled whose witnesses around it (the 26 neighbours, shown, facing its way) have a mean
residual beyond `SURE` standard deviations of their noise and above `STRAY` times the
tolerance is *stray*: the light changes there within a texel or two in a way no pair of
nodes spans (the top layer of a band at a contact, where the layer below the texel is lit
twice as brightly; light that bends across a facing change), and it is traced instead.
Decided from traced values alone, per texel: the same for any worker count, and on resume.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from isolume.baking import octahedral
from isolume.baking.density_kernels import node_at
from isolume.baking.sided import FACING_POWER, sided_mix
from isolume.volumes import cores
from isolume.volumes.field import JIT

SURE = 3.0
"""Standard deviations of its noise an error measured from traced texels must exceed
before it counts: a brick's surpluses' sum of squares (`baking.density.noise_free_rms`),
a leaning fill's slope (`drift_error`), the witnesses' mean residual (`stray_fills`)."""
DRIFT = 0.25
"""Texels along an axis the centre of a fill's side-aware weights may lie from the texel
before the fill is judged as an extrapolation along that axis (`drift_error`)."""
STRAY = 3.0
"""The least mean residual, in units of the tolerance (`NodeLight.allowed`), that makes a
texel to be filled stray."""
BLOCK = 1 << 15
"""Texels one item of the check takes, at most."""
OFFSETS = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], np.int64) - 1
"""(26, 3) z, y, x steps to a texel's neighbours."""


@dataclass
class NodeLight:
    """The traced light a fill is judged by: (T,) `luminance`, (T,) `error` variances of
    the texels' means, (T,) bool `shown` (`baking.fills.shown_texels`), the error a fill
    may make (`allowed`: the tolerance times the scene's light level) and (T,) bool the
    nodes on an edge of the light (`baking.density.fine_bricks`; None: not judged), each
    over the plan's texels."""

    luminance: np.ndarray
    error: np.ndarray
    shown: np.ndarray
    allowed: float
    edges: np.ndarray | None = None

    def weigh(self, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(N, 8) `weights` of the shown nodes among (N, 8) plan positions `rows`
        (`shown_weights`)."""
        return shown_weights(rows, weights, self.shown)


def shown_weights(rows: np.ndarray, weights: np.ndarray, shown: np.ndarray) -> np.ndarray:
    """(N, 8) `weights` of the nodes at (N, 8) plan positions `rows` (−1: none) that the
    (T,) bool `shown` marks, 0 for the others."""
    return np.where((rows >= 0) & shown[np.maximum(rows, 0)], weights, 0.0)


def drift_error(nodes: Any, coords: np.ndarray, rows: np.ndarray, weights: np.ndarray,
                sides: np.ndarray, facing: np.ndarray, own_facing: np.ndarray,
                light: NodeLight, floor: float) -> np.ndarray:
    """(N,) the error, beyond its noise, of a fill whose side-aware weights centre more
    than `DRIFT` texels from its texel along an axis: there it holds the nodes' light flat
    past them, and errs by the light's slope along that axis — read from each node and
    the next node beyond it that faces the texel's way, less `SURE` standard deviations
    of its noise — times the distance. Where the slope cannot be read (most of the weight
    has no such node beyond it), infinite if the sides made the lean (the nodes across
    the texel are there but face away: between two surfaces that nearly touch, where the
    light changes fastest), else 0 (the texel lies past the last layer of nodes, at the
    edge of the baked band: nothing to read a slope from, and nothing there that shows
    more than the band's edge). 0 for a centred fill.

    Args:
        coords: (N, 3) the texels' z, y, x; rows: (N, 8) plan positions of their nodes
            (`Nodes.corners`); weights: (N, 8) the shown nodes' trilinear weights;
            sides: (N, 8) their side weights (`node_sides`).
        facing: (T, 2) every texel's octahedral facing; own_facing: (N, 2) the texels';
            floor: the least side weight of a node beyond (`baking.density.SIDE_FLOOR`).
    """
    squares = np.zeros(len(rows))
    _drift_squares(nodes.rows, nodes.coords, nodes.offset, np.asarray(coords, np.int64),
                   np.asarray(rows, np.int64), np.asarray(weights, np.float64),
                   np.asarray(sides, np.float64), facing, own_facing, light.luminance,
                   light.error, light.shown, floor, FACING_POWER, squares)
    return np.sqrt(squares)


@numba.njit(**JIT)
def _drift_squares(node_rows: np.ndarray, node_coords: np.ndarray, offset: int,
                   coords: np.ndarray, rows: np.ndarray, weights: np.ndarray,
                   sides: np.ndarray, facing: np.ndarray, own_facing: np.ndarray,
                   luminance: np.ndarray, error: np.ndarray, shown: np.ndarray,
                   floor: float, power: int, squares: np.ndarray) -> None:
    """`drift_error`'s squares into (N,) `squares`, per texel (see there for the
    arguments; `node_rows`, `node_coords`, `offset`: the half lattice's `Nodes.rows`,
    `Nodes.coords`, `Nodes.offset`), summed as numpy sums the arrays: over a texel's 8
    nodes pairwise (`_sum8`), over the nodes of each axis's lean in order."""
    share, plain_share, part = np.empty(8), np.empty(8), np.empty(8)
    slopes, noises = np.empty(8), np.empty(8)
    drift, plain = np.empty(3), np.empty(3)
    spots = np.empty((8, 3), np.int64)
    for n in range(rows.shape[0]):
        for k in range(8):
            share[k] = weights[n, k] * sides[n, k]
            spots[k] = node_coords[max(rows[n, k], 0)]
        _to_shares(share)
        plain_share[:] = weights[n]
        _to_shares(plain_share)
        for axis in range(3):
            drift[axis] = share[0] * (spots[0, axis] - coords[n, axis])
            plain[axis] = plain_share[0] * (spots[0, axis] - coords[n, axis])
            for k in range(1, 8):
                drift[axis] += share[k] * (spots[k, axis] - coords[n, axis])
                plain[axis] += plain_share[k] * (spots[k, axis] - coords[n, axis])
        cx, cy = own_facing[n, 0], own_facing[n, 1]
        known = cx != 0 or cy != 0
        nx, ny, nz = octahedral.decode_pair(int(cx), int(cy))
        for axis in range(3):
            step = drift[axis]
            if not abs(step) > DRIFT:
                continue
            beyond = 2 if step > 0 else -2
            for k in range(8):
                far = node_at(node_rows,
                              (spots[k, 0] - offset + (beyond if axis == 0 else 0)) // 2,
                              (spots[k, 1] - offset + (beyond if axis == 1 else 0)) // 2,
                              (spots[k, 2] - offset + (beyond if axis == 2 else 0)) // 2)
                ok = far >= 0 and shown[far] and (not known or octahedral.side_of(
                    facing[far, 0], facing[far, 1], nx, ny, nz, power) >= floor)
                part[k] = share[k] if ok else 0.0
                near, far = max(rows[n, k], 0), max(far, 0)
                slopes[k] = part[k] * (luminance[near] - luminance[far])
                noises[k] = part[k] ** 2 * (error[near] + error[far])
            covered = _sum8(part)
            held = max(covered, 1e-12)
            slope = _sum8(slopes) / held
            noise = _sum8(noises) / held ** 2
            if covered >= 0.5:
                miss = max(abs(slope) - SURE * np.sqrt(noise), 0.0) * 0.5 * abs(step)
                squares[n] += miss ** 2
            elif abs(step - plain[axis]) > DRIFT:
                squares[n] += np.inf


@numba.njit(**JIT)
def _sum8(values: np.ndarray) -> float:
    """The sum of (8,) `values` in numpy's pairwise order for eight."""
    return (((values[0] + values[1]) + (values[2] + values[3]))
            + ((values[4] + values[5]) + (values[6] + values[7])))


@numba.njit(**JIT)
def _to_shares(weights: np.ndarray) -> None:
    """(8,) `weights` over their sum (`_sum8`), in place; 0 where the sum is 0."""
    total = _sum8(weights)
    for k in range(8):
        weights[k] = weights[k] / total if total > 0 else 0.0


def node_sides(rows: np.ndarray, facing: np.ndarray, own_facing: np.ndarray) -> np.ndarray:
    """(N, K) side weights (`baking.sided.side_weights`, compiled:
    `octahedral.side_rows`) of the texels at (N, K) plan positions `rows` (8 nodes, or 26
    neighbours; their (T, 2) `facing`) for texels facing (N, 2) `own_facing` (1 where it
    is unknown)."""
    sides = octahedral.side_rows(rows, facing, octahedral.decode(own_facing), FACING_POWER)
    return np.where(octahedral.known(own_facing)[:, None], sides, 1.0)


def node_mix(rows: np.ndarray, weights: np.ndarray, facing: np.ndarray,
             own_facing: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(N, C) the side-aware mix (`sided_mix`) of the (T, C) `values` of the nodes at
    (N, 8) plan positions `rows` with (N, 8) `weights`, for texels whose facings are
    (N, 2) `own_facing` (unknown: the plain mix); `facing`: (T, 2) every texel's."""
    return sided_mix(weights, node_sides(rows, facing, own_facing),
                     values[np.maximum(rows, 0)].astype(np.float64))


def residuals(nodes: Any, coords: np.ndarray, at: np.ndarray, facing: np.ndarray,
              luminance: np.ndarray, shown: np.ndarray) -> np.ndarray:
    """(N,) the half lattice `nodes`' side-aware mix of its shown nodes' (T,) `luminance`
    at the texels of plan positions (N,) `at`, less theirs (NaN where no shown node has
    weight).

    Args:
        nodes: a half lattice (`baking.fills.Nodes`); coords: (T, 3) the plan's
            texels' z, y, x; facing: (T, 2) octahedral facings; shown: (T,) bool, what a
            display shows.
    """
    rows, w = nodes.corners(coords[at])
    w = shown_weights(rows, w, shown)
    mix = node_mix(rows, w, facing, facing[at], luminance[:, None])[:, 0]
    return np.where(w.sum(axis=1) > 0, mix - luminance[at], np.nan)


def stray_fills(lattices: list[Any], fills: list[np.ndarray], coords: np.ndarray,
                ids: np.ndarray, shape: tuple[int, int, int], witness: np.ndarray,
                light: NodeLight, facing: np.ndarray, floor: float) -> np.ndarray:
    """The sorted plan positions, among each half lattice's `fills`, of the stray texels
    (see the module's docs).

    Args:
        lattices: the half lattices (`baking.fills.Nodes`), in the order of `fills`.
        coords: (T, 3) z, y, x of the plan's texels, whose (T,) sorted flat lattice `ids`
            in a (Z, Y, X) `shape`; witness: (T,) bool, the traced texels that are not
            nodes.
        light: the traced light (luminance, error, shown, allowed); facing: (T, 2)
            octahedral facings; floor: the least side weight of a witness
            (`baking.density.SIDE_FLOOR`; 1 where a texel's facing is unknown).
    """
    seen = np.flatnonzero(witness & light.shown)
    stray = []
    for nodes, filled in zip(lattices, fills, strict=True):
        residual = np.full(len(coords), np.nan)

        def measure(part: slice, nodes: Any = nodes, residual: np.ndarray = residual) -> None:
            at = seen[part]
            residual[at] = residuals(nodes, coords, at, facing, light.luminance, light.shown)

        cores.for_blocks(measure, len(seen), BLOCK, "texels", least=cores.GLUE_BLOCK)
        out = np.zeros(len(filled), bool)

        def judge(part: slice, filled: np.ndarray = filled, residual: np.ndarray = residual,
                  out: np.ndarray = out) -> None:
            at = filled[part]
            near = neighbours_of(coords[at], ids, shape)
            safe = np.maximum(near, 0)
            ok = ((near >= 0) & ~np.isnan(residual[safe])
                  & (node_sides(near, facing, facing[at]) >= floor))
            count = ok.sum(axis=1)
            mean = np.where(ok, residual[safe], 0.0).sum(axis=1) / np.maximum(count, 1)
            noise = np.where(ok, light.error[safe], 0.0).sum(axis=1) / np.maximum(count, 1) ** 2
            beyond = np.abs(mean) - SURE * np.sqrt(noise)
            out[part] = (count > 0) & (beyond > STRAY * light.allowed)

        cores.for_blocks(judge, len(filled), BLOCK, "texels", least=cores.GLUE_BLOCK)
        stray.append(filled[out])
    return np.sort(np.concatenate(stray)) if stray else np.zeros(0, np.int64)


def neighbours_of(at: np.ndarray, ids: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """(N, 26) plan positions of the neighbours of the texels at (N, 3) z, y, x `at`
    (−1: outside the lattice or not in the plan), from the plan's sorted flat `ids`, in
    one compiled pass without the GIL (`_neighbour_rows`)."""
    out = np.empty((len(at), len(OFFSETS)), np.int64)
    _neighbour_rows(np.ascontiguousarray(at), ids, np.array(shape, np.int64), OFFSETS, out)
    return out


@numba.njit(**JIT)
def _neighbour_rows(at: np.ndarray, ids: np.ndarray, shape: np.ndarray, offsets: np.ndarray,
                    out: np.ndarray) -> None:
    """out[i, j]: the plan position of the texel at at[i] + offsets[j] ((K, 3) z, y, x
    steps), by binary search in the sorted flat `ids` of a (3,) `shape` lattice; −1
    where it lies outside or is not in the plan."""
    for i in range(at.shape[0]):
        for j in range(offsets.shape[0]):
            z = np.int64(at[i, 0]) + offsets[j, 0]
            y = np.int64(at[i, 1]) + offsets[j, 1]
            x = np.int64(at[i, 2]) + offsets[j, 2]
            out[i, j] = -1
            if 0 <= z < shape[0] and 0 <= y < shape[1] and 0 <= x < shape[2]:
                flat = (z * shape[1] + y) * shape[2] + x
                found = np.searchsorted(ids, flat)
                if found < len(ids) and ids[found] == flat:
                    out[i, j] = found
