"""Noise-driven sampling: paths where the noise is (`BakeConfig.target_error`).

A bake with a target (`baking.bake.bake_to_target`, from the parts here) traces its
texels one level group at a time (the texels whose lower level is l, `Plan.lower`; their
two level scenes stay cached through the group's rounds), in deterministic rounds on a
ladder of sample counts (`ladder`): `BakeConfig.samples` (the minimum), twice that, and
so on up to `BakeConfig.max_samples`. After each round every texel of the group still
going is judged (`still_going`): it needs paths in proportion to the spread of its paths'
brightness (`path_spread`), scaled so that the group's root-mean-square standard error is
the target times the group's light level (`group_brightness`: the isosurface a picture
is exposed for, so dark texels are not chased to a relative precision no pixel shows),
and goes on while doubling keeps it within √2 of that. Its spread is taken as at least
the median of its neighbours' in the group (`neighbour_variance`), so no texel stops on a
handful of paths that agree by chance (all blocked, all open sky) while the texels around
it say the light there varies, and a texel with no light at all goes on until a display
can tell it trapped in a sealed pocket.

The same bits whoever traces: a texel's paths and sums depend on it alone (`baking.passes`)
and every judgement is made from the lattice as a finished round left it. The state of
the round under way — its group, rung, the group's light level and mean spread, and which
of its texels go on (`ROUND_KEY` in the lattice's metadata, saved with every checkpoint:
`RoundState`) — lets an interrupted bake resume with the same decisions; a finished one is
left as it is. A bake of a file finished to another target (or ladder) starts over from
group 0 with the texels' samples as they are: a lower target adds paths to them.
"""

from __future__ import annotations

import base64
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from isolume.baking import kernels
from isolume.baking.density import texel_luminance
from isolume.baking.lattice import (
    LUMINANCE,
    TRAPPED_PATHS,
    Lattice,
    path_variance,
    sky_everywhere,
)
from isolume.volumes import cores

ROUND_KEY = "rounds"
"""The lattice metadata's record of an adaptive bake (`RoundState.record`)."""
NEIGHBOUR_BLOCK = 1 << 16
"""Texels whose neighbours' variances one item of `neighbour_variance` gathers."""


def ladder(least: int, most: int) -> list[int]:
    """The rungs of sample counts: `least`, 2·`least`, … and `most` last (`most` ≥ `least`)."""
    rungs = [least]
    while rungs[-1] < most:
        rungs.append(min(2 * rungs[-1], most))
    return rungs


@dataclass
class RoundState:
    """Where an adaptive bake to `target` on the ladder `least` … `most` stands: the level
    `group` it traces, the `rung` (index into `ladder`) of its round under way, the
    group's `brightness` (None before its first round is judged) and mean `spread`, the
    `going` (N,) bool mask of the group's texels in that round (None: all of them), and
    whether every group is `finished`."""

    target: float
    least: int
    most: int
    group: int = 0
    rung: int = 0
    brightness: float | None = None
    spread: float = 0.0
    going: np.ndarray | None = None
    finished: bool = False

    def record(self) -> dict[str, Any]:
        """JSON-ready: the mask as zlib-deflated `numpy.packbits`, base64."""
        going = None
        if self.going is not None:
            packed = zlib.compress(np.packbits(self.going).tobytes(), 6)
            going = {"count": len(self.going), "bits": base64.b64encode(packed).decode()}
        return {"target": self.target, "least": self.least, "most": self.most,
                "group": self.group, "rung": self.rung, "brightness": self.brightness,
                "spread": self.spread, "going": going, "finished": self.finished}

    @classmethod
    def resumed(cls, record: dict[str, Any] | None, target: float, least: int,
                most: int) -> RoundState:
        """The state to go on from: `record` (a lattice's ``meta[ROUND_KEY]``) where it is
        a bake of the same target and ladder (finished: nothing is left to do), else a
        start from group 0."""
        fresh = cls(target, least, most)
        if (not record or (record.get("target"), record.get("least"), record.get("most"))
                != (target, least, most)):
            return fresh
        if record.get("finished"):
            return cls(target, least, most, finished=True)
        going = record.get("going")
        mask = None
        if going is not None:
            bits = np.frombuffer(zlib.decompress(base64.b64decode(going["bits"])), np.uint8)
            mask = np.unpackbits(bits, count=int(going["count"])).astype(bool)
        return cls(target, least, most, int(record["group"]), int(record["rung"]),
                   record.get("brightness"), float(record.get("spread", 0.0)), mask)


def group_brightness(luminance: np.ndarray) -> float:
    """The light level of a level group: the mean of its (N,) texels' brightness (> 0;
    1 where every texel is dark, so that the target is then an absolute one)."""
    level = float(np.mean(np.abs(luminance))) if len(luminance) else 0.0
    return level if level > 0 else 1.0


def neighbour_variance(ids: np.ndarray, variance: np.ndarray, shape: tuple[int, int, int],
                       which: np.ndarray) -> np.ndarray:
    """(K,) median per-path variance of the neighbours (26-connected, in the same group)
    of the texels at positions (K,) `which` of a group of (N,) sorted flat lattice `ids`
    of a (Z, Y, X) box, whose (N,) variances are `variance`; 0 for a texel with none.
    Compiled (`kernels.neighbour_medians`), `NEIGHBOUR_BLOCK` texels an item, on every
    core."""
    out = np.zeros(len(which))
    ids = np.asarray(ids, np.int64)
    variance = np.asarray(variance, np.float64)
    which = np.asarray(which, np.int64)

    def gather(part: slice) -> None:
        kernels.neighbour_medians(ids, variance, *shape, which[part], out[part])

    cores.for_blocks(gather, len(which), NEIGHBOUR_BLOCK, "adaptive")
    return out


def path_spread(luminance: np.ndarray, second: np.ndarray, samples: np.ndarray,
                ids: np.ndarray, shape: tuple[int, int, int], which: np.ndarray
                ) -> np.ndarray:
    """(K,) per-path standard deviation of the brightness of the texels at positions (K,)
    `which` of a group (its (N,) means `luminance`, mean squares `second`, `samples`, at
    sorted flat lattice `ids` of a (Z, Y, X) `shape` box): the larger of their own and
    their neighbours' median (`neighbour_variance`)."""
    variance = path_variance(luminance, second, samples)
    return np.sqrt(np.maximum(variance[which],
                              neighbour_variance(ids, variance, shape, which)))


def still_going(spread: np.ndarray, samples: np.ndarray, brightness: float,
                mean_spread: float, target: float, most: int, dark: np.ndarray,
                dark_until: int, step: float = 2.0) -> np.ndarray:
    """(K,) bool: which of K texels with per-path standard deviations `spread` and
    `samples` go on to the next rung (`step` times their samples: twice on the bake's
    ladder, four times in the viewer's rounds); (K,) `dark`: those whose
    paths all brought no light, which go on below `dark_until` samples whatever their
    spread.

    The paths a texel needs are in proportion to its spread (the allocation of a fixed
    number of paths that least noise leaves in the group, summed over its texels), scaled
    so that the group's root-mean-square standard error is `target` × its `brightness`
    (`mean_spread`: the group's mean spread): n* = spread · mean_spread / (target ·
    brightness)². A texel goes on while the next rung keeps it within √`step` of n*, and
    below `most`.

    Texels without light: under a sky that lights every direction, a texel whose paths
    all stayed in a pocket sealed from the sky is trapped, and a display leaves it out
    once it rests on `baking.lattice.TRAPPED_PATHS` paths (`Lattice.shown`); decided on
    fewer, it would be drawn black. So there `dark_until` is that count.
    """
    need = spread * mean_spread / (target * brightness) ** 2
    return (samples < most) & ((samples * float(np.sqrt(step)) < need)
                               | (dark & (samples < dark_until)))


def relative_error(values: np.ndarray, second: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(N,) estimated relative standard error of texel means: SE(luminance) / luminance.

    Args:
        values: (N, C) running means (irradiance RGB: luminance from C = 3; else channel 0).
        second: (N,) mean squared per-path luminance.
        samples: (N,) paths averaged.

    Returns:
        (N,) float64; inf where fewer than 2 samples (no variance estimate yet).
    """
    lum = values[:, :3] @ LUMINANCE if values.shape[1] >= 3 else values[:, 0]
    se = np.sqrt(path_variance(lum, second, samples) / np.maximum(samples, 1))
    return np.where(samples > 1, se / np.maximum(np.abs(lum.astype(np.float64)), 1e-12),
                    np.inf)


def round_going(lattice: Lattice, weights: np.ndarray, ids: np.ndarray, target: int,
                target_error: float, step: int, shape: tuple[int, int, int]) -> np.ndarray:
    """(N,) bool: which texels of a group (the viewer's lazy bake's visible or surface
    texels, at the (N,) flat `ids` of `lattice`'s (Z, Y, X) `shape` box) a round to
    `target` paths, `step` times the last round's, refines: `still_going`'s rule, as the
    bake's rounds judge their groups (their brightness the (C,) `weights` of the values,
    the one their second moments hold: the bake's `tracing.weights`), and those without
    paths yet."""
    ids = np.asarray(ids, np.int64)
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    samples = lattice.samples.reshape(-1)[sorted_ids].astype(np.int64)
    luminance = texel_luminance(lattice.values.reshape(-1, len(weights))[sorted_ids],
                                weights)
    second = lattice.second.reshape(-1)[sorted_ids]
    lit = samples > 0
    spread = path_spread(luminance, second, samples, sorted_ids, shape,
                         np.arange(len(sorted_ids)))
    going = ~lit | still_going(
        spread, samples, group_brightness(luminance[lit]),
        float(np.mean(spread[lit])) if lit.any() else 0.0, target_error, target,
        luminance == 0, TRAPPED_PATHS if sky_everywhere(lattice.config) else 0, step)
    out = np.empty(len(ids), bool)
    out[order] = going
    return out
