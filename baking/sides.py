"""Which side of its level surface each texel is lit on.

A texel stores the light arriving on one side of the surface through it. The paper lights
the side its normals point to (lower values: the outside of a dense object). That is the
side a camera outside the volume sees on a closed object, and the wrong one where the
surface is a sheet seen from its high side — the Richtmyer–Meshkov mixing surface, the
Marschner–Lobb function, a scan cut by the box (the inside of a pot, a leg, a skull seen
through the cut): lit on the normals' side, those texels would carry the light of the
folds and pockets of the side nobody sees.

`choose_sides` asks the level surface itself: from each texel's point on its nearer level,
`PROBES` rays leave each side, cosine-distributed about its normal; a side is *open* when
some ray leaves the volume without meeting the surface (a camera outside the box, looking
back along that ray, sees that side there). The side other than the normals' is probed
only where the volume lets it be open: where none of the corners of the probes' cell
connects to the box's faces through values beyond the level (`volumes.reach.BoxReach`,
one flood per bake), it is closed without a ray — the inside of every closed object, and
where a probe's origin lies a hair beyond the level but outside the marching-cubes
surface that approximates it, whose rays leave through the gap between the two (8 and 27
of 20 000 points of the tooth CT's levels 150.5 and 190.5, with 1–5 of 16 rays out). A
texel is lit on its open side; where both are open, on the normals' side where it has
clearly more open rays, else on alternate sides in a 3D checkerboard, so that the
side-aware lookup (`baking.octahedral`, ``shaders/lattice.glsl``) finds texels facing
either way among any eight neighbours; where neither is (a closed cavity), on the
normals' side.

The side other than the normals' is lit alone only where the normals' side is closed:
where it is open too, it is mostly the inside of the material seen through the box's cut
— the floor under the engine CT's arches, a slab the box cuts across, whose inside sees
the whole sky through the cut (16 of 16 rays) while the default camera sees its top face
through the arch (1–3 of 16). Lit there alone, the side the camera sees would have no
texels and be drawn in the cut's light: 2.6 times too bright on the engine's floor (its
default view, lit at 256 paths under a constant sky: 10.2 % RMS against path tracing,
2.2 % with the checkerboard). So a normals' side none of whose `PROBES` rays left, where
the other side is open, gets `CONFIRM_PROBES` more before it is taken for closed. Sheets
seen from their high side pay a little for the hedge (the Richtmyer–Meshkov bakes of the
accuracy sweep: 8.56 → 9.00 % and 7.18 → 7.58 %; docs/accuracy.md). The probe directions
hash (seed, texel, ray), so the choice is the same bits whoever computes it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.baking import kernels
from isolume.baking.plan_kernels import LandedStarts, NearerLandings
from isolume.baking.rng import seed_key
from isolume.baking.side_kernels import probe_sides
from isolume.volumes import cores
from isolume.volumes.reach import BoxReach

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.trace import Scene

PROBES = 16
"""Rays per side and texel. A side a tenth of whose rays would leave is found with
probability 1 − 0.9¹⁶ = 0.81; the 3D checkerboard makes a texel missed there cost half its
neighbours' weight, not a black patch."""
CONFIRM_PROBES = 48
"""More rays on the normals' side of a texel whose other side is open and whose normals'
side met the surface with all of its first `PROBES`: a side that a twentieth of the rays
would leave is then found with probability 1 − 0.95⁶⁴ = 0.96. Only texels whose other
side is open (a solid the box cuts, a cavity in one that fills the box, a sheet) and
whose normals' side looked closed trace them."""
CLEARLY_MORE = 8.0
"""Both sides open: the normals' side, where its fraction of open rays is this many times
the other's, is lit alone, else both in a checkerboard. Texels of a plate across the box
find their outer side a few times more open than the plate's inside; lit alone there,
the side-aware lookup finds enough texels facing each face (the lit face of a plate 2
voxels thick keeps 0.96 of its light at 8 times, 0.88 at 16, 0.74 with no such side)."""
PROBE_OFFSET_VOXELS = 0.25
"""Least distance of a probe's origin from the surface (the bake's offset when larger)."""
SALT = 0x51DE_5EED
"""Mixed into the bake seed: the probes use random numbers of their own."""
TEXELS_PER_BATCH = 1024
"""Texels one work item probes (`_probe_level`; 16 384 rays, 0.6 MB of rays): a level of
a few ten thousand texels is still dozens of items for the cores to share."""


def choose_sides(volume: volumes.Volume, config: BakeConfig, geometry: LatticeGeometry,
                 ids: np.ndarray, nearer: NearerLandings,
                 found: np.ndarray, levels: np.ndarray, which_level: np.ndarray,
                 scenes: Callable[[int], object] | None = None,
                 progress: Callable[[float], None] | None = None,
                 box_reach: Callable[[], BoxReach] | None = None) -> np.ndarray:
    """(T,) bool: is texel `ids[t]` lit on its surface's high-value side?

    Args:
        ids: (T,) flat lattice ids of the texels (their checkerboard parity and probe keys).
        nearer: where the texels land on their nearer level (of the same `ids`); found:
            (T,) bool, whether a texel has such a point (else it is lit on the normals'
            side).
        levels: (K,) isovalues; which_level: (T,) index of each texel's nearer level.
        scenes: ``scenes(k)``, the Embree scene of level k from the baker's cache (no
            scene beside the baker's), or None to build each here (`level_surface`);
            levels are probed highest first, so that the one left in the baker's cache
            is the lowest, where its tracing starts.
        progress: told the fraction of the found texels probed so far, after each batch
            of `TEXELS_PER_BATCH` texels the calling thread probes.
        box_reach: ``box_reach()``, the flood of `volume` towards the side other than
            the normals' (`BoxReachAhead.get`), or None to flood it here.
    """
    default = bool(config.flip_normals)
    high = np.full(len(ids), default)
    total, probed = max(int(np.count_nonzero(found)), 1), 0
    # where the other side can be open
    reach = box_reach() if box_reach is not None else BoxReach.of(volume, up=not default)
    for k in np.unique(which_level[found])[::-1]:
        on = np.flatnonzero(found & (which_level == k))
        scene = scenes(int(k)) if scenes is not None else None
        if scene is None:
            scene = level_surface(volume, float(levels[k]))
        if not scene.empty:
            _probe_level(scene, volume, config, geometry, ids, nearer, on, float(levels[k]),
                         default, reach, high, _fraction(progress, probed, total))
        probed += len(on)
        del scene  # gone before the next level's is built
    return high


class BoxReachAhead:
    """The flood `choose_sides` tests the side other than the normals' against
    (`BoxReach.of` towards it), begun on a pool thread early in the plan (`begin`), so
    that it runs beside the plan's stages rather than alone before the probes (one core
    for 1.4 s on the 256³ foot CT, 17.6 s on the 512³ one) — or, with one thread, where
    the sides are chosen from the normals, or from inside the pool, made when first
    asked for (`get`). A context: leaving it stops a flood still running (an interrupted
    plan), within `volumes.reach.FLOOD_POPS` voxels."""

    def __init__(self, volume: volumes.Volume, config: BakeConfig) -> None:
        self._volume, self._up = volume, not bool(config.flip_normals)
        self._probed = config.sides == "seen"
        self._stop = threading.Event()
        self._ahead: cores.Beside | None = None

    def begin(self) -> None:
        """Start the flood on a pool thread, where the sides are probed and the pool has
        a thread to spare for it (`cores.ahead`)."""
        if self._probed:
            self._ahead = cores.ahead("box reach", BoxReach.of, self._volume, self._up,
                                      self._stop)

    def get(self) -> BoxReach:
        """The flood: the pool thread's (waited for), or made now where none began it."""
        if self._ahead is None or self._ahead.cancel():
            return BoxReach.of(self._volume, self._up)
        return self._ahead.wait()

    def __enter__(self) -> BoxReachAhead:
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        if self._ahead is not None:
            self._ahead.cancel()


def _fraction(progress: Callable[[float], None] | None, probed: int, total: int):
    """``told(texels)``: `progress` told the fraction of `total` texels probed, `probed`
    before this level and `texels` on it (nothing without `progress`)."""
    if progress is None:
        return lambda _texels: None
    return lambda texels: progress((probed + texels) / total)


def _probe_level(scene, volume: volumes.Volume, config: BakeConfig,
                 geometry: LatticeGeometry, ids: np.ndarray, nearer: NearerLandings,
                 on: np.ndarray, level: float, default: bool, reach: BoxReach,
                 high: np.ndarray, told: Callable[[int], None]) -> None:
    """Choose the sides of the texels at positions `on` (M,) of one level into `high`, a
    `TEXELS_PER_BATCH` at a time on every core (`cores.for_items`): each item finds its
    texels' points, normals and probe origins, traces their probes and applies the rule —
    in one compiled call (`side_kernels.probe_sides`), or on a scene without compiled
    Embree calls in arrays and embreex (`open_rays`)."""
    blocks = -(-len(on) // TEXELS_PER_BATCH)
    if scene.calls is not None:
        item = _compiled_item(scene, volume, config, geometry, ids, nearer, on, level,
                              default, reach, high)
    else:
        def item(b: int) -> None:
            at = on[b * TEXELS_PER_BATCH:(b + 1) * TEXELS_PER_BATCH]
            open_low, open_high, rays = open_rays(scene, volume, config, ids[at],
                                                  nearer.points(at), level, default, reach)
            high[at] = side_rule(open_low, open_high, parity(geometry, ids[at]), default,
                                 rays)

    cores.for_items(item, blocks, "side probes",
                    on_done=lambda done: told(min(done * TEXELS_PER_BATCH, len(on))))


def _compiled_item(scene, volume: volumes.Volume, config: BakeConfig,
                   geometry: LatticeGeometry, ids: np.ndarray, nearer: NearerLandings,
                   on: np.ndarray, level: float, default: bool, reach: BoxReach,
                   high: np.ndarray) -> Callable[[int], None]:
    """``item(b)``: `side_kernels.probe_sides` of the b-th `TEXELS_PER_BATCH` texels of
    `on`, with what every item shares made once (the plan's `ids` as they are, int32 in
    a box of fewer than 2³¹ texels: an int64 copy of the 512³ foot's 41 M took 0.8 s of
    one core at each level)."""
    value_type = np.result_type(volume.data.dtype, np.float32)  # `volumes.value_at`'s
    starts = LandedStarts.of(volume, geometry, config, nearer.reach)
    fixed = (scene.calls, np.uint32(seed_key(config.seed ^ SALT)), starts.lattice, ids)
    landing = (nearer.upper, nearer.landing, starts.step, starts.field, starts.weights,
               probe_offset(volume, config), value_type.type(level))
    tested = (True, *reach.arrays(volume))

    def item(b: int) -> None:
        probe_sides(*fixed, on[b * TEXELS_PER_BATCH:(b + 1) * TEXELS_PER_BATCH], *landing,
                    np.empty(1, value_type), PROBES, CONFIRM_PROBES, bool(default),
                    CLEARLY_MORE, tested, high)

    return item


def probe_offset(volume: volumes.Volume, config: BakeConfig) -> float:
    """How far off the surface a probe starts, world units: the bake's offset, at least
    `PROBE_OFFSET_VOXELS` (of the mean spacing)."""
    return max(config.offset, PROBE_OFFSET_VOXELS) * float(np.mean(volume.spacing))


def side_rule(open_low: np.ndarray, open_high: np.ndarray, odd: np.ndarray,
              default: bool, rays: np.ndarray | int = PROBES) -> np.ndarray:
    """(N,) bool high sides from the (N,) counts of open probe rays on the low and the
    high side, of `PROBES` rays on the side other than the `default` one and (N,) `rays`
    on the default side, and the (N,) checkerboard parity `odd` (see the module docs)."""
    both = (open_low > 0) & (open_high > 0)
    mine, other = (open_high, open_low) if default else (open_low, open_high)
    clearly_mine = mine * PROBES >= CLEARLY_MORE * other * np.asarray(rays)
    high = np.where(open_high > 0, True, np.where(open_low > 0, False, default))
    return np.where(both, np.where(clearly_mine, default, odd), high)


def parity(geometry: LatticeGeometry, ids: np.ndarray) -> np.ndarray:
    """(N,) bool: is the sum of the texels' (z, y, x) indices odd?"""
    k, j, i = np.unravel_index(np.asarray(ids, np.int64), geometry.shape)
    return ((k + j + i) & 1).astype(bool)


def level_surface(volume: volumes.Volume, iso: float) -> Scene:
    """Embree scene of the level surface ρ = `iso` (the one the bake traces)."""
    from isolume.baking.trace import Scene

    vertices, faces = volumes.tracing_surface(volume, iso)
    return Scene(vertices, faces)


def open_rays(scene: Scene, volume: volumes.Volume, config: BakeConfig, ids: np.ndarray,
              points: np.ndarray, level: float, default: bool, reach: BoxReach | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How many of `PROBES` rays, cosine-distributed about each side's normal from the
    (N, 3) `points` on the level ρ = `level` (offset from the surface along that normal),
    meet nothing. Cosine-distributed, because a camera sees a patch in proportion to its
    projected area. None, on a side whose offset origin does not lie on that side of the
    level (a wall or a fold thinner than the offset: a path from there would start on the
    other side).

    The side other than the `default` one (high-value when False) is probed first; the
    default side only where that one is open, since where it is closed `side_rule` lights
    the default side whatever the default side's count (left 0 there). On a closed object
    that halves the rays. The other side is not probed where `reach` (the volume's
    `BoxReach` towards that side) proves it closed. Where the other side is open and none
    of the default side's rays left, `CONFIRM_PROBES` more of them are traced. Arrays and
    embreex (`unblocked_rays`), for a scene without compiled Embree calls
    (`side_kernels.probe_sides` does the same in one call).

    Returns:
        open_low, open_high: (N,) int counts for the low- and the high-value side;
        rays: (N,) int rays behind the default side's count.
    """
    normals = volumes.normals_at(volume, points, smooth=config.normals == "smooth"
                                 ).astype(np.float64)  # towards low values
    offset = probe_offset(volume, config)
    key = np.uint32(seed_key(config.seed ^ SALT))

    def count(sign: float, which: np.ndarray, first: int = 0, probes: int = PROBES,
              tested: BoxReach | None = None) -> np.ndarray:
        out = np.zeros(len(points), np.int64)
        origins = points[which] + sign * offset * normals[which]
        if tested is not None and len(origins):
            open_there = tested.may_open(volume, origins, level)
            which = which.copy()
            which[which], origins = open_there, origins[open_there]
        if which.any():
            unblocked = unblocked_rays(scene, key, ids[which], origins,
                                       sign * normals[which], first, probes)
            beyond = volumes.value_at(volume, origins) - level
            on_side = beyond < 0 if sign > 0 else beyond > 0
            out[which] = np.where(on_side, unblocked, 0)
        return out

    other_sign = 1.0 if default else -1.0  # the low side's normal is +normals
    other = count(other_sign, np.ones(len(points), bool), tested=reach)
    mine = count(-other_sign, other > 0)
    confirmed = (other > 0) & (mine == 0)
    mine += count(-other_sign, confirmed, PROBES, CONFIRM_PROBES)
    rays = np.where(confirmed, PROBES + CONFIRM_PROBES, PROBES)
    return (other, mine, rays) if default else (mine, other, rays)


def unblocked_rays(scene: Scene, key: np.uint32, ids: np.ndarray, origins: np.ndarray,
                   normals: np.ndarray, first: int = 0, probes: int = PROBES) -> np.ndarray:
    """(N,) int: how many of the `probes` rays of each point (keys as the paths of samples
    `first` … `first` + `probes` − 1 of texel `ids[i]` under the seed key `key`,
    cosine-distributed about the (N, 3) `normals` from the (N, 3) `origins`) meet
    nothing. Compiled rays (`kernels.path_starts`) traced by embreex `TEXELS_PER_BATCH`
    texels at a time on every core, so memory stays bounded: for a scene without compiled
    calls
    (`side_kernels.open_counts` does the same)."""
    n = len(ids)
    out = np.empty(n, np.int64)
    ids = np.asarray(ids, np.int64)
    origins = np.ascontiguousarray(origins, np.float32)
    normals = np.ascontiguousarray(normals, np.float32)
    samples = np.tile(np.arange(first, first + probes, dtype=np.int64), TEXELS_PER_BATCH)

    def batch(b: int) -> None:
        lo = b * TEXELS_PER_BATCH
        hi = min(lo + TEXELS_PER_BATCH, n)
        texels = np.arange(hi - lo, dtype=np.int64)
        pos = np.repeat(texels, probes)
        _, starts, _, dirs = kernels.path_starts(key, ids[lo:hi], pos,
                                                 samples[:len(pos)], texels,
                                                 origins[lo:hi], normals[lo:hi])
        blocked = scene.occluded(starts.T, dirs.T)
        out[lo:hi] = probes - blocked.reshape(-1, probes).sum(axis=1)

    cores.for_items(batch, -(-n // TEXELS_PER_BATCH), "probe rays")
    return out
