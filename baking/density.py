"""Texels where the light varies: bricks of the lattice traced at half resolution where
that reproduces their light (`BakeConfig.texel_error`).

The lattice is cut into `BRICK`³ bricks (those of the renderer's GPU atlas). Its *nodes*
are the active texels whose z, y and x are all even: a lattice at half the resolution,
nested in the full one (node k at texel 2k), so that at any texel the trilinear mix of its
surrounding nodes is exactly what a display's trilinear lookup of the half lattice shows
there. A bake to a texel error (`bake_texels`):

1. traces every node — the even ones, and the odd ones (z, y, x all odd: the other half
   lattice) around the texels whose even nodes face away from them (`odd_nodes_needed`:
   where both sides of a sheet are lit in a checkerboard, `baking.sides`, the even nodes
   lie on one colour of it), chosen from the plan's facings before any path;
2. judges each brick by its *surpluses*: at each of its nodes and along each of 13
   directions (the axes, the face and the body diagonals), the node's light less the
   mean of the two nodes a step of the half lattice either side of it, where both are
   shown and face its way — the error of linear interpolation at four texels' spacing
   (more along a diagonal). Their mean square at each node, and the root of its mean over
   the brick's nodes, less what the nodes' path noise accounts for and `SURE` standard
   deviations of that (`noise_free_rms`: noise alone does not make a brick fine; a node's
   pairs share its noise, so each node counts once), estimates that error; at two
   texels' spacing, the fill's, it is `EDGE_SHARE` of it (the error falls as the spacing
   where the light has an edge, as its square where it is smooth: the half is the
   cautious one). A brick whose
   estimate is above `texel_error` times the scene's light level (`light_level`) is
   *fine*; so is a brick without a single pair to judge by;
3. traces the other texels of the fine bricks, and every texel that neither half lattice
   can fill (`split_texels`): no shown node around it facing its way (`SIDE_FLOOR`);
   shown nodes on one side of it only (the others missing: the fill would extrapolate)
   that face its way less closely (`ONE_SIDED_FLOOR` — in the gap under a sphere that
   rests on a plane, a texel of one surface beside a node of the other); or a node of its
   mix on an edge of the light (`EDGE_NODE`: that node's own surpluses, beyond their
   noise, where its brick's mean hides them — a contact, a shadow's edge in a corner);
   or a fill that leans to one side, off by more than the tolerance where the light has
   a slope (`drift_error`: e.g. in the gap between two surfaces that nearly touch);
4. gives the nodes that fill texels `NODE_PATHS` times `samples` paths, with step 3's
   texels (their light is spread over the filled texels around them); traces the texels
   to be filled whose traced neighbours contradict the fill (*stray*:
   `baking.fill_check.stray_fills`, `trace_strays`); and fills the rest (*filled*
   texels) with the side-aware mix of their nodes (`baking.fills.fill`: `sided_mix`, what
   the shader does with the half lattice), their facings from the plan as a traced
   texel's.

Under a sky from every direction, a traced texel whose paths all stayed dark — a node
before the judgement, any other once step 3 is traced — goes on to
`baking.lattice.TRAPPED_PATHS` paths (`dark_to_trapped`): decided on fewer, a display
would draw it black; on that many it is either lit or known to be trapped in a sealed
pocket and left out of the lookups. So `samples` below that costs no black pixels.

The lattice stays one uniform grid that every reader reads as it is, seamless by
construction (a filled brick is the half lattice's trilinear field, sampled at its own
texels). Decisions are made from finished node values alone and per texel, so the same
seed gives the same lattice for any worker count or backend; the decisions are kept in
the lattice's metadata (`JUDGED_KEY`, `Judgement`), so that a resumed bake makes the same
ones. The filled texels are recorded there too, with what makes their fill again
(`FILLED_KEY`, `baking.fills.Recipe`: a file leaves their light out and its reader mixes
it again from the nodes); a later bake of the same file first clears them
(`clear_filled`), so that a resumed, a finer or a uniform bake never takes a filled texel
for a traced one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from isolume.baking.config import NODE_PATHS
from isolume.baking.density_kernels import node_pair_surpluses
from isolume.baking.fill_check import SURE, NodeLight, drift_error, node_sides, stray_fills
from isolume.baking.fills import (
    FILLED_KEY,
    Nodes,
    Recipe,
    fill,
    filled_positions,
    mask_of,
    packed,
    shown_texels,
    texel_coords,
    texel_luminance,
    unpacked,
)
from isolume.baking.lattice import (
    BRICK,
    TRAPPED_PATHS,
    brick_grid,
    path_variance,
    sky_everywhere,
)
from isolume.baking.passes import commit_facing
from isolume.baking.sided import FACING_POWER
from isolume.volumes import cores

JUDGED_KEY = "texel_judgement"
"""The lattice metadata's record of a bake's decisions (`Judgement`)."""
SIDE_FLOOR = 0.5
"""The least side-aware share of the weight (`side_share`) a texel is filled on, and the
least side weight of a node's pair in its surplus."""
EDGE_SHARE = 0.5
"""The error of the half-resolution fill, per unit of the quarter-resolution surplus."""
EDGE_NODE = 3.0
"""A node whose own surpluses, beyond their noise, put the fill's error above this many
times the tolerance is on an edge of the light (a contact, a shadow's edge): the texels
whose mix it is part of are traced, whatever its brick's mean says."""
ONE_SIDED_FLOOR = 0.8
"""The least side-aware share (`side_share`) a texel is filled on from nodes that carry
at most half of its trilinear weight (the others missing or not shown: the texel lies
past the half lattice's edge, and the fill extrapolates from one side of it)."""
BLOCK = 1 << 16
"""Texels one item of the judging passes takes, at most."""
DIRECTIONS = np.array([d for d in np.ndindex(3, 3, 3)
                       if np.ravel_multi_index(d, (3, 3, 3)) > 13], np.int64) - 1
"""(13, 3) z, y, x steps of the half lattice to the neighbours of a node on one side
(the other 13 of its 26 are their opposites): the axes, the face and the body diagonals."""


def brick_of(coords: np.ndarray, grid: tuple[int, int, int]) -> np.ndarray:
    """(N,) flat indices, over the (BZ, BY, BX) `grid` (`brick_grid`), of the bricks
    holding the texels at (N, 3) z, y, x `coords`."""
    return np.ravel_multi_index(tuple((coords // BRICK).T), grid)


def texel_bricks(coords: np.ndarray, grid: tuple[int, int, int]) -> np.ndarray:
    """(T,) `brick_of` all (T, 3) texel `coords`, a block at a time on every core: int32
    (4 bytes a texel, held through the judgement) where the `grid` has fewer than 2³¹
    bricks."""
    small = int(np.prod(grid)) < np.iinfo(np.int32).max
    bricks = np.empty(len(coords), np.int32 if small else np.intp)

    def part(block: slice) -> None:
        bricks[block] = brick_of(coords[block], grid)

    cores.for_blocks(part, len(coords), BLOCK, "texels", least=cores.GLUE_BLOCK)
    return bricks


def mixing_mask(nodes: Nodes, coords: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(T,) bool over the plan's (T, 3) texels `coords`: the `nodes` with a weight in the
    trilinear mix of a texel at plan positions (N,) `at` (`Nodes.corners`), marked a
    block of texels at a time on every core."""
    used = np.zeros(len(coords), bool)

    def mark(block: slice) -> None:
        rows, weights = nodes.corners(coords[at[block]])
        used[rows[weights > 0]] = True

    cores.for_blocks(mark, len(at), BLOCK, "texels", least=cores.GLUE_BLOCK)
    return used


def light_level(luminance: np.ndarray) -> float:
    """The scene's light level: the mean brightness of the (N,) node luminances (1 where
    every node is dark: the tolerance is then an absolute one)."""
    level = float(np.mean(np.abs(luminance))) if len(luminance) else 0.0
    return level if level > 0 else 1.0


def noise_free_rms(squares: np.ndarray, noise: np.ndarray, noise_squares: np.ndarray,
                   counts: np.ndarray) -> np.ndarray:
    """(B,) root-mean-square of bricks' surpluses beyond their noise:
    √(max(Σs² − Σσ² − `SURE`·√(2 Σσ⁴), 0) / n) from (B,) sums of the squared surpluses s²,
    of their noise variances σ² and of σ⁴, and (B,) counts n (0 where n = 0). Where the
    surpluses are Gaussian noise of those variances, Σs² has mean Σσ² and standard
    deviation √(2 Σσ⁴)."""
    excess = np.maximum(squares - noise - SURE * np.sqrt(2.0 * noise_squares), 0.0)
    return np.sqrt(np.divide(excess, counts, out=np.zeros_like(excess), where=counts > 0))


def pair_surpluses(nodes: Nodes, at: np.ndarray, luminance: np.ndarray,
                   error: np.ndarray, shown: np.ndarray, facing: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 13) surpluses of the nodes at plan positions (N,) `at` along the 13 directions
    of `DIRECTIONS`: a node's brightness less the mean of the two nodes a step of the half
    lattice either side of it (0 where either is missing, not `shown`, or faces away:
    side weight below `SIDE_FLOOR`), and (N, 13) their noise variances from the (T,)
    `error` variances of the texels' means (NaN where there is no pair).

    Args:
        luminance: (T,) brightness; shown: (T,) bool, what a display shows;
        facing: (T, 2) octahedral facings.
    """
    surplus = np.zeros((len(at), len(DIRECTIONS)))
    noise = np.full((len(at), len(DIRECTIONS)), np.nan)
    node_pair_surpluses(nodes.rows, nodes.half(at), np.asarray(at, np.int64), DIRECTIONS,
                        np.asarray(luminance, np.float64), np.asarray(error, np.float64), shown,
                        facing, SIDE_FLOOR, FACING_POWER, surplus, noise)
    return surplus, noise


def fine_bricks(lattices: list[Nodes], bricks: np.ndarray, light: NodeLight,
                facing: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B,) bool over the flat (⌈Z/8⌉, ⌈Y/8⌉, ⌈X/8⌉) bricks, twice: those the half
    lattices do not reproduce within the error the traced `light` allows (see the
    module's docs), and those holding a texel of the plan; and (T,) bool the nodes on an
    edge of the light (`EDGE_NODE`: a node's pairs share its noise, so its surpluses are
    one term of `noise_free_rms`).

    Args:
        lattices: the traced half lattices (the even nodes; the odd ones where traced);
            bricks: (T,) the brick of each of the plan's texels (`texel_bricks`);
            facing: (T, 2) octahedral facings.
    """
    count = int(np.prod(brick_grid(lattices[0].shape)))
    luminance, error, shown = light.luminance, light.error, light.shown
    sums = np.zeros((4, count))
    edges = np.zeros(len(bricks), bool)
    for nodes in lattices:
        at = nodes.positions
        per_node = np.zeros((4, len(at)))

        def judge(part: slice, nodes: Nodes = nodes, at: np.ndarray = at,
                  per_node: np.ndarray = per_node) -> None:
            surplus, var = pair_surpluses(nodes, at[part], luminance, error, shown, facing)
            has = ~np.isnan(var)
            pairs = has.sum(axis=1)
            judged = np.maximum(pairs, 1)
            square = np.where(has, surplus ** 2, 0.0).sum(axis=1) / judged
            noise = np.where(has, var, 0.0).sum(axis=1) / judged
            noise_squares = noise ** 2
            per_node[:, part] = [square, noise, noise_squares, pairs > 0]
            own = noise_free_rms(square, noise, noise_squares, 1.0 * (pairs > 0))
            edges[at[part]] = EDGE_SHARE * own > EDGE_NODE * light.allowed

        cores.for_blocks(judge, len(at), BLOCK, "texels", least=cores.GLUE_BLOCK)
        sums += [np.bincount(bricks[at], v, count) for v in per_node]
    every = np.bincount(bricks, minlength=count) > 0
    rough = EDGE_SHARE * noise_free_rms(*sums) > light.allowed
    return every & (rough | (sums[3] == 0)), every, edges


def facing_away(nodes: Nodes, at: np.ndarray, coords: np.ndarray, facing: np.ndarray,
                light: NodeLight | None = None) -> np.ndarray:
    """(N,) bool: the texels at plan positions (N,) `at` that the half lattice `nodes`
    cannot fill: their nodes' side-aware weight (`side_share`) below `SIDE_FLOOR`, or below
    `ONE_SIDED_FLOOR` where those nodes carry at most half of the trilinear weight; and,
    judged by the traced `light` (None: before any path, every active node counted), a
    node of their mix on an edge of the light, or a fill leaning to one side that errs by
    more than it allows (`drift_error`)."""
    away = np.zeros(len(at), bool)

    def look(part: slice) -> None:
        here = coords[at[part]].astype(np.int64)
        rows, w = nodes.corners(here)
        w = np.where(rows >= 0, w, 0.0) if light is None else light.weigh(rows, w)
        sides = node_sides(rows, facing, facing[at[part]])
        share = side_share(w, sides)
        one_sided = w.sum(axis=1) <= 0.5 + 1e-9
        away[part] = (share < SIDE_FLOOR) | (one_sided & (share < ONE_SIDED_FLOOR))
        if light is not None:
            if light.edges is not None:
                away[part] |= ((w * sides > 0) & light.edges[np.maximum(rows, 0)]).any(axis=1)
            away[part] |= drift_error(nodes, here, rows, w, sides, facing,
                                      facing[at[part]], light, SIDE_FLOOR) > light.allowed

    cores.for_blocks(look, len(at), BLOCK, "texels", least=cores.GLUE_BLOCK)
    return away


def odd_nodes_needed(even: Nodes, coords: np.ndarray, facing: np.ndarray,
                     others: np.ndarray) -> np.ndarray:
    """The plan positions of the odd nodes to trace: the active ones around the texels
    among (K,) `others` whose even nodes face away from them (every active even node
    counted: nothing is traced yet), sorted."""
    away = others[facing_away(even, others, coords, facing)]
    return np.flatnonzero(mixing_mask(Nodes(coords, tuple(even.shape), 1), coords, away))


def split_texels(lattices: list[Nodes], coords: np.ndarray, fine: np.ndarray,
                 facing: np.ndarray, light: NodeLight
                 ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The plan positions of the texels that are not nodes: those in fine bricks ((T,)
    bool `fine`, per texel), those of the others that are traced all the same (*alone*:
    no half lattice can fill them, `facing_away` — e.g. the other side of a sheet, lit in
    a checkerboard, `baking.sides`, where only the even nodes are traced; nodes on one
    side of them only, facing less closely; a node on an edge of the light among them; a
    fill that would extrapolate a slope), and per half lattice of `lattices` (in order),
    those it fills; sorted arrays."""
    others = np.flatnonzero(~mask_of(len(coords), *(n.positions for n in lattices)))
    in_fine = fine[others]
    left = others[~in_fine]
    fills = []
    for lattice in lattices:
        away = facing_away(lattice, left, coords, facing, light)
        fills.append(left[~away])
        left = left[away]
    return others[in_fine], left, fills


def side_share(weights: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """(N,) the side-aware weight of nodes with (N, 8) `weights` and (N, 8) `sides`
    (`node_sides`), over the plain weight (0 where no node has weight)."""
    plain = weights.sum(axis=1)
    sided = (weights * sides).sum(axis=1)
    return np.divide(sided, plain, out=np.zeros_like(plain), where=plain > 0)


@dataclass
class Judgement:
    """What a bake to a texel error decided once its nodes were traced: the (B,) `fine`
    bricks, and the plan positions each half lattice fills (`fills`: even, odd). Kept in
    the lattice's metadata (`JUDGED_KEY`) from then on, so that a resumed bake, or the
    same bake of a finished file — whose nodes have more paths by then — goes on with
    the same decisions."""

    fine: np.ndarray
    fills: list[np.ndarray]

    def record(self, config: Any, total: int) -> dict[str, Any]:
        """JSON-ready, for a bake of `config` over `total` texels."""
        return {"texel_error": config.texel_error, "samples": config.samples,
                "count": total, "bricks": len(self.fine),
                "fine": packed(self.fine),
                "fills": [packed(mask_of(total, f)) for f in self.fills]}

    @classmethod
    def resumed(cls, record: dict[str, Any] | None, config: Any, total: int
                ) -> Judgement | None:
        """The judgement of `record` where it is of a bake of `config`'s texel error and
        samples over `total` texels, else None."""
        if not record or (record.get("texel_error"), record.get("samples"),
                          record.get("count")) != (config.texel_error, config.samples, total):
            return None
        fine = np.zeros(int(record["bricks"]), bool)
        fine[unpacked(record["fine"], len(fine))] = True
        return cls(fine, [unpacked(f, total) for f in record["fills"]])


def clear_filled(lattice: Any, plan_size: int, texel_bake: bool) -> np.ndarray:
    """Take the filled texels of an earlier bake out of `lattice` (over the plan's
    texels, `PlanLattice`): no samples, values nor moments, and drop the record, so a
    bake goes on from traced texels alone; a bake that is not to a texel error
    (`texel_bake` False) drops an unfinished one's judgement too.

    Returns:
        (F,) int64 plan positions of the texels taken out (none: empty).

    Raises:
        ValueError: the record is of another plan (another texel count).
    """
    if not texel_bake:
        lattice.meta.pop(JUDGED_KEY, None)
    record = lattice.meta.pop(FILLED_KEY, None)
    if record is None:
        return np.zeros(0, np.int64)
    if int(record["count"]) != plan_size:
        raise ValueError(f"the lattice's filled texels are of a plan of {record['count']:,} "
                         f"texels, this one has {plan_size:,}")
    at = filled_positions(record)
    lattice.samples.reshape(-1)[at] = 0
    lattice.values.reshape(plan_size, -1)[at] = 0
    lattice.second.reshape(-1)[at] = 0
    return at


def refilled(lattice: Any, config: Any, cleared: np.ndarray, plan_size: int) -> np.ndarray:
    """Those of the (F,) plan positions `cleared` (`clear_filled`) that a bake of `config`
    fills again, tracing none of their paths: all where it goes on with the judgement
    `lattice` records (`Judgement.resumed`: a finished texel bake run again), else none."""
    if config.texel_error is None or Judgement.resumed(
            lattice.meta.get(JUDGED_KEY), config, plan_size) is None:
        return cleared[:0]
    return cleared


def bake_texels(baker: Any, bar: Any, checkpoint: Any) -> None:
    """Bake `baker`'s texels (a `baking.bake.Baker` holding a `PlanLattice`) to its
    config's `texel_error` at `samples` paths a texel: nodes, judgement, the fine bricks'
    texels and more paths for the nodes that fill, dark texels on to the trapped count,
    the fill (see the module's docs); the record in the metadata."""
    config, lattice = baker.config, baker.lattice
    shape = baker.geometry.shape
    coords = texel_coords(baker.plan.ids, shape)
    total = len(coords)
    even = Nodes(coords, shape)
    make_facings(baker)
    facing = lattice.facing.reshape(-1, 2)
    node = mask_of(total, even.positions)
    odd = Nodes(coords, shape, 1, odd_nodes_needed(even, coords, facing,
                                                   np.flatnonzero(~node)))
    node[odd.positions] = True
    nodes = np.flatnonzero(node)
    trapped_at = TRAPPED_PATHS if sky_everywhere(config) else 0
    later = int(np.maximum(config.samples - baker.samples_done(np.flatnonzero(~node)),
                           0).sum())  # the bar's estimate of the passes after the nodes'
    _trace(baker, nodes, config.samples, bar, checkpoint, restart=True, later=later)
    dark_to_trapped(baker, nodes, trapped_at, bar, checkpoint, later)
    dark_share = (np.mean(baker.samples_done(nodes) == trapped_at)
                  if trapped_at and len(nodes) else 0.0)
    weights = baker.job.tracing.weights
    judged = Judgement.resumed(lattice.meta.get(JUDGED_KEY), config, total)
    bricks = texel_bricks(coords, brick_grid(shape))
    if judged is None:
        judged = judge(baker, [even, odd], coords, bricks, facing, trapped_at)
        lattice.meta[JUDGED_KEY] = judged.record(config, total)
    in_fine = ~node & judged.fine[bricks]
    filled = mask_of(total, *judged.fills)
    alone = ~(node | in_fine | filled)
    even_fills, odd_fills = judged.fills
    filling = mixing_mask(even, coords, even_fills) | mixing_mask(odd, coords, odd_fills)
    traced = np.flatnonzero(in_fine | alone | filling)
    paths = np.where(filling[traced], NODE_PATHS * config.samples, config.samples)
    record = {  # kept once the fill is made; the masks go before the second pass
        "texel_error": config.texel_error, "count": total,
        "even_nodes": len(even.positions), "odd_nodes": len(odd.positions),
        "filling_nodes": int(filling.sum()), "in_fine_bricks": int(in_fine.sum()),
        "alone": int(alone.sum()),
        "fine_bricks": int(judged.fine.sum()),
        "bricks": int(np.count_nonzero(np.bincount(bricks)))}
    witness = in_fine | alone
    del node, nodes, in_fine, filled, alone, filling, bricks
    dark_later = dark_share * np.count_nonzero(paths < trapped_at) * (trapped_at
                                                                      - config.samples)
    _trace(baker, traced, paths, bar, checkpoint, later=int(dark_later))  # as dark as the nodes
    dark_to_trapped(baker, traced, trapped_at, bar, checkpoint)
    del traced, paths
    stray = trace_strays(baker, [even, odd], judged.fills, coords, witness, trapped_at, bar,
                         checkpoint)
    del witness
    fills = [np.setdiff1d(part, stray, assume_unique=True) for part in judged.fills]
    samples = lattice.samples.reshape(-1)
    shown = shown_texels(texel_luminance(lattice.values.reshape(total, -1), weights), samples,
                         trapped_at)
    filled = mask_of(total, *fills)
    record.update(trapped=int(np.count_nonzero((samples > 0) & ~shown)), stray=len(stray),
                  filled=int(filled.sum()), bits=packed(filled),
                  **Recipe.record(odd.positions, fills[1], weights, trapped_at, total))
    for half, part in zip((even, odd), fills, strict=True):
        fill(lattice, half, coords, part, shown, config.samples)
    lattice.meta[FILLED_KEY] = record


def trace_strays(baker: Any, lattices: list[Nodes], fills: list[np.ndarray],
                 coords: np.ndarray, witness: np.ndarray, trapped_at: int, bar: Any,
                 checkpoint: Any) -> np.ndarray:
    """Trace the stray texels among the half `lattices`' `fills` (`stray_fills`, judged by
    the (T,) bool `witness` texels: traced, not nodes) at `samples` paths, dark ones on to
    `trapped_at` (`dark_to_trapped`), and return their sorted plan positions."""
    light = traced_light(baker, len(coords), lattices[0].positions, trapped_at)
    stray = stray_fills(lattices, fills, coords, baker.plan.ids, baker.geometry.shape,
                        witness, light, baker.lattice.facing.reshape(-1, 2), SIDE_FLOOR)
    _trace(baker, stray, baker.config.samples, bar, checkpoint)
    dark_to_trapped(baker, stray, trapped_at, bar, checkpoint)
    return stray


def traced_light(baker: Any, total: int, level_at: np.ndarray, trapped_at: int
                 ) -> NodeLight:
    """The traced light of `baker`'s lattice over its `total` plan texels (`NodeLight`):
    luminance, the variances of the texels' means, what a display shows, and the error a
    fill may make — the texel error times the light level of the texels at plan positions
    `level_at` (the even nodes: `light_level`)."""
    lattice = baker.lattice
    luminance = texel_luminance(lattice.values.reshape(total, -1), baker.job.tracing.weights)
    samples, second = lattice.samples.reshape(-1), lattice.second.reshape(-1)
    variance = np.empty(total)

    def part(block: slice) -> None:
        variance[block] = path_variance(luminance[block], second[block],
                                        samples[block]) / np.maximum(samples[block], 1)

    cores.for_blocks(part, total, BLOCK, "texels", least=cores.GLUE_BLOCK)
    return NodeLight(luminance, variance,
                     shown_texels(luminance, samples, trapped_at),
                     baker.config.texel_error * light_level(luminance[level_at]))


def dark_to_trapped(baker: Any, positions: np.ndarray, trapped_at: int, bar: Any,
                    checkpoint: Any, later: int = 0) -> None:
    """Trace on to `trapped_at` paths (0: none, under lights that leave texels honestly
    dark) the texels among plan `positions` (sorted) whose light is all zero on fewer: a
    display draws such a texel black, where once it rests on `TRAPPED_PATHS` it is known
    to be trapped in a sealed pocket and left out of the lookups (`Lattice.shown`), and a
    texel that sees a little sky is lit. So fewer paths a texel than that cost no black
    pixels. The progress `bar` counts `later` paths still to come after these."""
    if trapped_at == 0 or len(positions) == 0:
        return
    values = baker.lattice.values.reshape(len(baker.plan.ids), -1)
    short = positions[baker.samples_done(positions) < trapped_at]
    dark = short[~values[short].any(axis=1)]
    if len(dark):
        _trace(baker, dark, trapped_at, bar, checkpoint, later=later)


def make_facings(baker: Any) -> None:
    """Every texel's facing (`commit_facing`) before any path, a level's texels at a time
    (their records one run of the plan's records), and the commits told to keep them."""
    for level in range(len(baker.plan.levels)):
        commit_facing(baker.lattice, baker.volume, baker.config, baker.plan, baker.records,
                      baker.groups.of(level), None)
    baker.facings_made = True


def judge(baker: Any, lattices: list[Nodes], coords: np.ndarray, bricks: np.ndarray,
          facing: np.ndarray, trapped_at: int) -> Judgement:
    """The fine bricks and the fills of `baker`'s lattice with its `lattices` of nodes
    traced (`fine_bricks`, `split_texels`; `bricks`: (T,) each texel's)."""
    light = traced_light(baker, len(coords), lattices[0].positions, trapped_at)
    fine, _, light.edges = fine_bricks(lattices, bricks, light, facing)
    _, _, fills = split_texels(lattices, coords, fine[bricks], facing, light)
    return Judgement(fine, fills)


def _trace(baker: Any, positions: np.ndarray, paths: int | np.ndarray, bar: Any,
           checkpoint: Any, restart: bool = False, later: int = 0) -> None:
    """Bring the texels at plan `positions` up to `paths` each (or (N,) per texel), the
    progress `bar` sized for them and `later` paths to come (`_count_paths`), a
    `checkpoint` after each commit."""
    _count_paths(bar, baker, positions, paths, restart, later)
    baker.run(positions, paths, bar=bar, after_commit=checkpoint)


def _count_paths(bar: Any, baker: Any, positions: np.ndarray, paths: int | np.ndarray,
                 restart: bool = False, later: int = 0) -> None:
    """Size the progress `bar` (None: none) for the paths the texels at plan `positions`
    still need to have `paths` each (or (N,) per texel), and the estimated `later` paths
    of passes to come: in place of its total (`restart`), or on top of what it has done.
    The total of a bake to a texel error is thus the outlook's until the fills are known,
    then what is left with its dark texels' paths estimated, then exactly, plus the stray
    texels' paths when they are found."""
    if bar is None:
        return
    wanted = int(np.maximum(paths - baker.samples_done(positions), 0).sum())
    bar.total = (wanted if restart else int(bar.n) + wanted) + later
    bar.refresh()
