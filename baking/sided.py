"""The side-aware lookup: a texel's light weighed by how its facing meets a point's normal.

Each texel of a lattice keeps the mean direction its paths started along, its *facing* m
(octahedral bytes, `baking.octahedral`). A point on a surface seen along the normal n
(turned to the eye) weights each of its 8 trilinear texels by max(0, n·m)^`FACING_POWER`
(1 for a texel of unknown facing), so a face of a wall thinner than two texels, or the
other side of a sheet, does not show light gathered on the opposite face; where no texel
faces its way, the plain trilinear mix is kept (`sided_mix`). `baking.lattice`'s lookups,
the fill of a bake to a texel error (`baking.fills`) and ``shaders/lattice.glsl`` mix so.
"""

from __future__ import annotations

import numpy as np

from isolume.baking import octahedral

FACING_POWER = 2
"""Exponent k of a texel's side weight max(0, n·m)^k in the side-aware lookup. Measured
on rods 1–2 voxels thick lit from above (rms error of E on their surface at 1 texel per
voxel): 0.23 plain, 0.15 with k = 1, 0.11 with k = 2; thin plates and a smooth sphere
alike for k = 1, 2 and 4."""
SIDE_BLEND = 0.1
"""The side-aware lookup is used whole where the side-weighted weight is at least this
fraction of the plain (valid-weighted) trilinear weight, and blends into the plain mix
below it (smoothstep from 0): where hardly any texel faces the point's way (a surface seen
from the side its texels were not lit on), one texel with a sliver of side weight must not
decide the colour — it made such points black."""


def side_weights(codes: np.ndarray, normals: np.ndarray,
                 power: int = FACING_POWER) -> np.ndarray:
    """(N, 8) side weights of N points' 8 lookup texels: max(0, n·m)^`power` for the
    texels' (N, 8, 2) facing `codes` (`baking.octahedral`) and the points' (N, 3) unit
    `normals` n (turned to the eye); 1 where a facing is unknown."""
    m = octahedral.decode(codes)
    cos = np.einsum("nkc,nc->nk", m, np.asarray(normals, np.float64))
    return np.where(octahedral.known(codes), np.maximum(cos, 0.0) ** power, 1.0)


def sided_mix(weights: np.ndarray, sides: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(N, C) the side-aware mix of (N, 8, C) texel `values` with (N, 8) lookup `weights`
    (trilinear × valid) and (N, 8) `sides` (`side_weights`): weighted by both and
    renormalised, blended into the plain (renormalised) mix by smoothstep(0, `SIDE_BLEND`)
    of the sided weight's fraction of the plain one. 0 where no texel has weight."""
    plain_w = weights.sum(axis=1, keepdims=True)
    sided_w = (weights * sides).sum(axis=1, keepdims=True)
    plain = _mean(weights, plain_w, values)
    sided = np.where(sided_w > 0, _mean(weights * sides, sided_w, values), plain)
    x = np.clip(np.divide(sided_w, plain_w, out=np.zeros_like(plain_w), where=plain_w > 0)
                / SIDE_BLEND, 0.0, 1.0)
    out = plain + x * x * (3.0 - 2.0 * x) * (sided - plain)
    return np.where(plain_w > 1e-6, out, 0.0)


def _mean(weights: np.ndarray, total: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(N, C) the (N, 8)-`weights`ed mean of (N, 8, C) `values` whose (N, 1) weight sum is
    `total` (0 where it is 0)."""
    num = np.einsum("nk,nkc->nc", weights, values)
    return np.divide(num, total, out=np.zeros_like(num), where=total > 0)
