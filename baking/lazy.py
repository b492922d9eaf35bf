"""Lazy, progressive baking for the isosurface on screen.

The paper (§4) suggests to "lazily perform computations as needed, assuming the display of
some uncomputed illumination is acceptable until computations are complete". This module
decides *which* texels to bake next and *how many* paths each gets; it knows nothing of GL,
windows or threads (`serve` is the loop a worker thread or process runs).

Which texels. A point p on the displayed isosurface ρ = iso is shaded by trilinear
interpolation of the 8 texels at the corners of the lattice cell that contains p: the
picture needs the corners of the cells whose corner values straddle iso ("surface
texels"), those under visible pixels first ("visible texels", found by the renderer from a
world-position pass), and within each group those nearest the eye first.

How many paths. Rounds of growing targets (4, 16, 64, ... up to the bake's sample count):
every texel of a group gets samples before any gets refined, and from `JUDGED_FROM` paths
on a round takes only the texels whose noise still shows at the group's light level
(`adaptive.round_going`, to `LAZY_TARGET_ERROR`). The stage order is visible@4,
visible@16, ..., then surface@4, surface@16, ...: what is on screen converges first.
Before any of it, the visible texels of every new view get previews traced on the
displayed surface (`baking.preview`): the picture is right within seconds, and the
texels' own values replace the previews once they rest on as many paths (a texel that
rests on fewer shows its preview until the lattice is opened again).

Batches and level scenes. Texels trace paths on their own isovalues' level surfaces
(`baking.plan`), and those around one isosurface use almost every level. A batch is one
`Baker.run` sweeping its texels' levels, each scene built once and kept while affordable
(the `ThreadBackend`'s scene memory); texels are committed (and shown) once their upper
level is traced, and a new view interrupts a batch between two commits.

Re-targeting. A new view (isovalue, eye, visible cells) rebuilds the stages; texels already
at a stage's target are skipped, so finished work is kept — a texel's value holds for its
own isosurface whatever isovalue is displayed, which is the point of the method.

A turned light. A lattice whose sun (or directional light) the display shades per pixel
holds that light's bounces; when the viewer turns it, `Relight` bakes the same texels in
the same order under the new direction (`relit_config`) into a lattice of its own, shown
texel by texel once it rests on `RELIGHT_PATHS` paths (no mean mixes two lights' paths).

Length: the stages, rounds, relighting and serving loop share one plan's arrays and views.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from isolume.baking.adaptive import round_going
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.plan import Plan

if TYPE_CHECKING:
    from isolume.baking.bake import Baker
    from isolume.baking.config import BakeConfig
    from isolume.volumes.core import Volume

FIRST_TARGET = 4
"""Paths per texel of the first round: enough for a recognisable estimate."""
TARGET_FACTOR = 4
"""Each round multiplies the target by this (halves the noise)."""
JUDGED_FROM = 64
"""Rounds to this many paths or more take only the texels whose noise still shows."""
LAZY_TARGET_ERROR = 0.02
"""Where the config sets none, the rounds' target: RMS standard error / the light level."""
REPORT_S = 1.0
"""Seconds between progress reports within a batch."""
BATCH_PATHS = 1 << 18
"""Paths per batch (one `Baker.run`): large, because every batch visits every level it
touches; a new view still interrupts a batch between two commits."""
VIEW_RANGE_FRACTION = 0.03
"""A lazy bake following the displayed isovalue serves this fraction of the data range on
either side of it (`view_iso_range`): texels beside steep surfaces are lit on its ends.
Sweep bakes at ±5/±3/±2 %: stent CT 15.7/10.6/10.5 %, hydrogen atom 5.2/4.7/8.6 % (fewer
levels under the scene-cost cap); docs/accuracy.md."""


def new_lattice(volume: Volume, config: BakeConfig) -> Lattice:
    """An empty lattice for `volume` baked with `config`, with the metadata `baking.bake`
    writes: what a lazy bake, or a surface's traced light, fills."""
    from isolume.baking.bake import lattice_meta, path_settings

    channels = path_settings(volume, config).channels
    return Lattice.empty(LatticeGeometry.for_volume(volume, config.scale), channels,
                         lattice_meta(volume, config, channels), config=config)


# -- the iso range around the displayed surface --------------------------------------------
def view_iso_range(volume: Volume, iso: float) -> tuple[float, float]:
    """The iso range a lazy bake for the isovalue `iso` serves: `VIEW_RANGE_FRACTION` of
    the data range on either side, within the data range. Its texels are lit on their
    values clamped to it (`baking.plan`): for the displayed surface that is more accurate
    than a wide range (texels lit close to it), and the plan, its active texels and its
    levels are a fraction of a wide range's."""
    vmin, vmax = volume.value_range
    half = VIEW_RANGE_FRACTION * (vmax - vmin)
    return max(vmin, iso - half), min(vmax, iso + half)


def carry_over(lattice: Lattice, old: Plan, new: Plan) -> np.ndarray:
    """Keep what a new plan (another iso range) can use of a lattice baked by `old`: a
    texel keeps its samples when both plans light it at the same target isovalue; the
    others are reset (values, second moments and sample counts to 0).

    Returns:
        (K,) flat ids of the texels reset (the display re-uploads them).
    """
    flat = old.ids
    target = np.full(len(flat), np.nan)
    pos = np.searchsorted(new.ids, flat)
    found = pos < len(new.ids)
    found[found] = new.ids[pos[found]] == flat[found]
    target[found] = new.target[pos[found]]
    samples = lattice.samples.reshape(-1)
    reset = flat[(target != old.target) & (samples[flat] > 0)]  # NaN: inactive now
    samples[reset] = 0
    lattice.values.reshape(-1, lattice.values.shape[-1])[reset] = 0
    lattice.second.reshape(-1)[reset] = 0
    return reset


# -- a turned light -------------------------------------------------------------------------
RELIGHT_PATHS = 16
"""Under a turned light a texel's new estimate goes on screen once it rests on this many
paths (its own or a preview's), or on as many as the old value it replaces when that had
fewer: until then the old light's value stays (stale, but not noisier than it was)."""
TURN_TOLERANCE_DEG = 0.5
"""Light directions closer than this are the same light (`app.viewer.draw.Drawing.light_note`
says "not turned" below it too)."""


def turned_light(config: BakeConfig) -> np.ndarray | None:
    """(3,) unit vector towards the light a viewer turns under `config`
    (`baking.lighting.Lighting.turnable`, the one `app.render.lights.aimed_lights` aims), or
    None when there is none or it is not shaded per pixel: a lattice holding its direct
    light, or an SH transfer (its sky and sun turn with the transfer; nothing to bake)."""
    if config.mode != "irradiance" or config.direct_light != "pixels":
        return None
    light = config.lighting.turnable()
    return None if light is None else np.asarray(light.direction, np.float64)


def same_direction(a: npt.ArrayLike, b: npt.ArrayLike) -> bool:
    """Whether unit vectors `a` and `b` (3,) lie within `TURN_TOLERANCE_DEG` of each other."""
    cos = float(np.dot(np.asarray(a, np.float64), np.asarray(b, np.float64)))
    return cos >= math.cos(math.radians(TURN_TOLERANCE_DEG))


def relit_config(config: BakeConfig, direction: np.ndarray) -> BakeConfig:
    """`config` with the light `turned_light` names pointing towards `direction` (3,)
    (`baking.lighting.Lighting.turned`); ValueError when it names none."""
    if turned_light(config) is None:
        env, lights = config.lighting.to_spec()
        raise ValueError(f"{env!r} {lights}: no per-pixel directional light or sun to turn")
    return config.with_lighting(config.lighting.turned(direction))


class Relight:
    """A lattice on screen baked again for a turned light (`relit_config`).

    The bake traces into `fresh`, a lattice of its own (means, sample counts, second
    moments and previews, all under the new light), and `publish` copies a texel's whole
    state from it into the lattice on screen, `shown`, once it rests on enough paths
    (`RELIGHT_PATHS`). Until then the display keeps the old light's value, and no texel's
    mean ever averages paths traced under two lights. A published texel follows `fresh`
    from then on (each `publish` of it copies it again).

    Args:
        shown: the lattice the display reads (the viewer's shared memory); its `active`
            mask is shared with `fresh`.
        config: the bake's config under the turned light.
        published: None, or a (Z, Y, X) bool array to keep `published` in (cleared; the
            viewer's shared memory, so that a saved lattice holds one light's texels).

    Attributes:
        fresh: the new light's lattice (what a `baking.bake.Baker` and a
            `baking.preview.Previewer` write into).
        published: (Z·Y·X,) bool, texels whose new estimate is on screen.
        direction: (3,) unit vector towards the turned light.
    """

    def __init__(self, shown: Lattice, config: BakeConfig,
                 published: np.ndarray | None = None) -> None:
        shape, channels = shown.samples.shape, shown.values.shape[-1]
        previews = shown.preview is not None
        # np.zeros: untouched pages cost no memory, and only the texels near the displayed
        # surface are ever written
        self.fresh: Lattice = Lattice(
            shown.geometry, np.zeros((*shape, channels), np.float32),
            np.zeros(shape, np.uint32), np.zeros(shape, np.float32), shown.active,
            dict(shown.meta),
            preview=np.zeros((*shape, channels), np.float32) if previews else None,
            preview_paths=np.zeros(shape, np.uint16) if previews else None, config=config)
        self.shown: Lattice = shown
        self.config: BakeConfig = config
        if published is None:
            published = np.zeros(shape, bool)
        published[...] = False
        self.published: np.ndarray = published.reshape(-1)
        self.direction: np.ndarray | None = turned_light(config)

    def needed(self, flat: np.ndarray) -> np.ndarray:
        """(K,) paths a new estimate of the texels `flat` (K,) needs to replace what the
        display shows of them now: `RELIGHT_PATHS`, or fewer when the old value rests on
        fewer (at least 1: a texel showing nothing shows any new estimate)."""
        old = _paths_behind(self.shown, flat)
        return np.maximum(np.minimum(old, RELIGHT_PATHS), 1)

    def publish(self, flat: np.ndarray) -> np.ndarray:
        """Put the new estimates of the texels `flat` (K,) on screen where they rest on
        enough paths (`needed`), or were published before; returns the (J,) flat ids
        copied (to be re-uploaded). The display (another process) may read them meanwhile
        (`Lattice.displayed`: the mean whose count is the larger): every count is lowered
        to the smaller of its two estimates' before the means are copied and set after,
        so that no count ever vouches for a mean half replaced (an old 8-path texel
        replaced by a 64-path preview read black between the two)."""
        flat = np.unique(np.asarray(flat, np.int64))
        if len(flat) == 0:
            return flat
        ready = self.published[flat] | (_paths_behind(self.fresh, flat) >= self.needed(flat))
        out = flat[ready]
        fresh, shown = self.fresh, self.shown
        counts = [(shown.samples.reshape(-1), fresh.samples.reshape(-1))]
        if shown.preview is not None:
            counts.append((shown.preview_paths.reshape(-1), fresh.preview_paths.reshape(-1)))
        for now, new in counts:  # lowered first: no count vouches for a mean being replaced
            now[out] = np.minimum(now[out], new[out])
        channels = shown.values.shape[-1]
        shown.values.reshape(-1, channels)[out] = fresh.values.reshape(-1, channels)[out]
        shown.second.reshape(-1)[out] = fresh.second.reshape(-1)[out]
        shown.facing.reshape(-1, 2)[out] = fresh.facing.reshape(-1, 2)[out]
        if shown.preview is not None:
            shown.preview.reshape(-1, channels)[out] = fresh.preview.reshape(-1, channels)[out]
            if fresh.preview_facing is not None:
                shown.ensure_preview_facing().reshape(-1, 2)[out] = \
                    fresh.preview_facing.reshape(-1, 2)[out]
        for now, new in reversed(counts):  # raised last: the means they vouch for are in
            now[out] = new[out]
        self.published[out] = True
        return out

    def forward(self, send: Callable[[tuple], None]) -> Callable[[tuple], None]:
        """A `serve` ``send`` that publishes the texels of each ``("texels", flat)``
        message (committed into `fresh`) and passes on those put on screen; other
        messages go to `send` unchanged."""
        def relay(message: tuple) -> None:
            if message[0] != "texels":
                send(message)
                return
            shown = self.publish(message[1])
            if len(shown):
                send(("texels", shown))

        return relay

    def status(self, scheduler: LazyScheduler) -> dict[str, Any]:
        """How far the view of `scheduler` (which bakes `fresh`) is on screen under the new
        light: counts of its visible and surface texels, and of those published."""
        ids = scheduler.plan.ids
        visible, surface = ids[scheduler.visible], ids[scheduler.surface]
        return {"direction": [float(v) for v in self.direction], "iso": scheduler.iso,
                "visible": len(visible), "visible_done": int(self.published[visible].sum()),
                "surface": len(surface), "surface_done": int(self.published[surface].sum())}


def _paths_behind(lattice: Lattice, flat: np.ndarray) -> np.ndarray:
    """(K,) int64 paths behind what a display shows of the texels `flat` (K,): the more
    of its own samples and its preview's paths."""
    paths = lattice.samples.reshape(-1)[flat].astype(np.int64)
    if lattice.preview_paths is not None:
        paths = np.maximum(paths, lattice.preview_paths.reshape(-1)[flat])
    return paths


# -- geometry of the texels the display needs ---------------------------------------------
def corner_offsets(shape: tuple[int, int, int]) -> np.ndarray:
    """(8,) int64 flat-index offsets of a cell's 8 corner texels from its (0, 0, 0) corner
    in a (Z, Y, X) lattice."""
    _, ny, nx = shape
    return np.array([dz * ny * nx + dy * nx + dx
                     for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], np.int64)


@dataclass(frozen=True)
class CellIndex:
    """Lattice cells whose 8 corners are all active texels, with their corner-value spans.

    Attributes:
        base: (M,) int64 flat texel id of each cell's (0, 0, 0) corner.
        lo, hi: (M,) float32 smallest and largest corner value (field units).
        offsets: (8,) int64 flat offsets of the corners from `base`.
    """

    base: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    offsets: np.ndarray


def cell_index(plan: Plan, shape: tuple[int, int, int]) -> CellIndex:
    """Index the cells of a (Z, Y, X) lattice whose corners are all active in `plan`.

    A cell with an inactive corner cannot be shaded from the lattice alone, and every cell
    the bake selected has all its corners active, so nothing the bake covers is lost.
    """
    z, y, x = shape
    active = np.zeros(z * y * x, bool)
    active[plan.ids] = True
    active = active.reshape(shape)
    inner = active[:-1, :-1, :-1].copy()
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                inner &= active[dz:z - 1 + dz, dy:y - 1 + dy, dx:x - 1 + dx]
    k, j, i = np.nonzero(inner)
    base = (k.astype(np.int64) * y + j) * x + i
    offsets = corner_offsets(shape)
    rho = np.full(z * y * x, np.nan, np.float32)
    rho[plan.ids] = plan.rho
    corners = rho[base[:, None] + offsets[None, :]]
    return CellIndex(base, corners.min(axis=1), corners.max(axis=1), offsets)


def positions_of(plan: Plan, flat_ids: np.ndarray) -> np.ndarray:
    """(K,) sorted unique plan positions (indices into ``plan.ids``) of the active texels
    among (N,) flat lattice ids; inactive ids are dropped."""
    flat = np.unique(np.asarray(flat_ids, np.int64))
    pos = np.searchsorted(plan.ids, flat)
    pos = np.minimum(pos, len(plan.ids) - 1)
    return pos[plan.ids[pos] == flat]


def surface_positions(plan: Plan, cells: CellIndex, iso: float) -> np.ndarray:
    """(K,) plan positions of the corners of the cells whose corner values straddle `iso`."""
    crossing = cells.base[(cells.lo <= iso) & (cells.hi >= iso)]
    return positions_of(plan, (crossing[:, None] + cells.offsets[None, :]).reshape(-1))


def visible_cells(geometry: LatticeGeometry, points: np.ndarray) -> np.ndarray:
    """(K,) unique flat ids of the (0, 0, 0) corners of the lattice cells that trilinear
    lookups at (N, 3) world `points` read (the cell containing each point, clamped to the
    lattice like GL's CLAMP_TO_EDGE)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    shape = np.array(geometry.shape)
    coords = geometry.to_texel_coords(np.asarray(points, np.float64))
    base = np.clip(np.floor(coords).astype(np.int64), 0, shape - 2)
    flat = (base[:, 0] * shape[1] + base[:, 1]) * shape[2] + base[:, 2]
    return np.unique(flat)


def footprint_positions(plan: Plan, shape: tuple[int, int, int],
                        cells: np.ndarray) -> np.ndarray:
    """(K,) plan positions of the active corner texels of cells given by (N,) flat base
    ids (from `visible_cells`)."""
    cells = np.asarray(cells, np.int64)
    return positions_of(plan, (cells[:, None] + corner_offsets(shape)[None, :]).reshape(-1))


def by_distance(plan: Plan, geometry: LatticeGeometry, positions: np.ndarray,
                eye: np.ndarray) -> np.ndarray:
    """(K,) `positions` sorted by the distance of their texel centres from `eye` (3,),
    nearest first (stable, so ties keep lattice order)."""
    if len(positions) == 0:
        return positions
    d = np.linalg.norm(geometry.centres(plan.ids[positions]) - np.asarray(eye, np.float64),
                       axis=1)
    return positions[np.argsort(d, kind="stable")]


def sample_targets(max_samples: int, first: int = FIRST_TARGET,
                   factor: int = TARGET_FACTOR) -> tuple[int, ...]:
    """Paths per texel of the successive rounds: first, first·factor, ... capped at (and
    ending with) `max_samples`. E.g. 100 → (4, 16, 64, 100)."""
    if max_samples < 1:
        raise ValueError(f"max_samples must be at least 1, got {max_samples}")
    targets, t = [], max(1, first)
    while t < max_samples:
        targets.append(t)
        t *= max(2, factor)
    targets.append(int(max_samples))
    return tuple(targets)


# -- the scheduler -------------------------------------------------------------------------
@dataclass
class Stage:
    """One round of one texel group: bring `positions` (in priority order) to `target`."""

    group: str
    target: int
    positions: np.ndarray
    cursor: int = 0
    judged: bool = False


@dataclass(frozen=True)
class Batch:
    """Work for one `Baker.run` call: plan positions and the paths each should reach."""

    positions: np.ndarray
    target: int
    group: str


@dataclass(frozen=True)
class Progress:
    """Where the lazy bake stands for the current view.

    Attributes:
        visible, visible_started: visible texels, and how many have ≥ 1 path.
        surface, surface_started: surface texels, and how many have ≥ 1 path.
        visible_min_samples: fewest paths of any visible texel (0 when none).
        stage: (group, target) being worked on, or None when the view is done.
        iso: isovalue of the view.
    """

    visible: int = 0
    visible_started: int = 0
    surface: int = 0
    surface_started: int = 0
    visible_min_samples: int = 0
    stage: tuple[str, int] | None = None
    iso: float | None = None

    @property
    def visible_fraction(self) -> float:
        """Share of visible texels with samples of their own (1 when there are none)."""
        return self.visible_started / self.visible if self.visible else 1.0

    @property
    def surface_fraction(self) -> float:
        """Share of surface texels with samples of their own (1 when there are none)."""
        return self.surface_started / self.surface if self.surface else 1.0

    @property
    def near_fraction(self) -> float:
        """Share of the texels near the displayed surface (visible ∪ surface) with samples
        of their own: what ``wait-bake`` waits for."""
        total = self.surface + self.visible
        return (self.surface_started + self.visible_started) / total if total else 1.0


class LazyScheduler:
    """Chooses the next batch of texels for the view on screen.

    Args:
        plan, geometry: the bake's plan and lattice geometry.
        samples: (Z·Y·X,) flat view of the lattice's per-texel sample counts; the baker
            writes into it, the scheduler only reads it.
        max_samples: the last round's target (the bake's `samples`).
        batch_paths: paths per batch.
        judged_by, target_error: the `Baker` of the `samples` and the noise target that
            judge rounds from `JUDGED_FROM` paths on (`adaptive.round_going`)
    """

    def __init__(self, plan: Plan, geometry: LatticeGeometry, samples: np.ndarray, *,
                 max_samples: int, batch_paths: int = BATCH_PATHS,
                 judged_by: Baker | None = None,
                 target_error: float = LAZY_TARGET_ERROR) -> None:
        self.plan: Plan = plan
        self.judged_by: Baker | None = judged_by
        self.target_error: float = float(target_error)
        self.geometry: LatticeGeometry = geometry
        self.samples: np.ndarray = samples
        self.targets: tuple[int, ...] = sample_targets(max_samples)
        self.batch_paths: int = max(1, int(batch_paths))
        self.cells: CellIndex = cell_index(plan, geometry.shape)
        self.stages: list[Stage] = []
        self.visible: np.ndarray = np.zeros(0, np.int64)
        self.surface: np.ndarray = np.zeros(0, np.int64)
        self.iso: float | None = None
        self._stage = 0

    def samples_at(self, positions: np.ndarray) -> np.ndarray:
        """(N,) paths done at plan `positions`."""
        return self.samples[self.plan.ids[positions]]

    def set_view(self, iso: float, eye: np.ndarray,
                 visible: np.ndarray | None = None) -> None:
        """Re-target the work: isovalue on screen, eye position (3,) world, and the flat
        base ids (K,) of the lattice cells under visible pixels (None: unknown)."""
        self.iso = float(iso)
        self.surface = by_distance(self.plan, self.geometry,
                                   surface_positions(self.plan, self.cells, iso), eye)
        if visible is not None and len(visible):
            vis = footprint_positions(self.plan, self.geometry.shape, visible)
            self.visible = by_distance(self.plan, self.geometry, vis, eye)
        else:
            self.visible = np.zeros(0, np.int64)
        # what is on screen converges first; the rest of the surface (seen once the camera
        # turns, when the new view's texels get previews at once, `baking.preview`)
        # follows in rounds of its own
        self.stages = [Stage("visible", t, self.visible) for t in self.targets
                       if len(self.visible)]
        self.stages += [Stage("surface", t, self.surface) for t in self.targets]
        self._stage = 0

    def next_batch(self) -> Batch | None:
        """The next texels to bake (priority order) and their target, or None when every
        stage of the current view is done."""
        while self._stage < len(self.stages):
            stage = self.stages[self._stage]
            self._judge(stage)
            window = stage.positions[stage.cursor:stage.cursor + self.batch_paths]
            if len(window) == 0:
                self._stage += 1
                continue
            remaining = np.maximum(stage.target - self.samples_at(window).astype(np.int64), 0)
            cum = np.cumsum(remaining)
            take = max(1, int(np.searchsorted(cum, self.batch_paths, side="right")))
            chosen = window[:take][remaining[:take] > 0]
            stage.cursor += take
            if len(chosen):
                return Batch(chosen, stage.target, stage.group)
        return None

    def _judge(self, stage: Stage) -> None:
        """Keep a `stage`'s texels still noisy (`round_going`), once, as it starts."""
        baker = self.judged_by
        if stage.judged or baker is None or stage.target < JUDGED_FROM:
            return
        stage.judged = True
        stage.positions = stage.positions[round_going(
            baker.lattice, baker.job.tracing.weights, self.plan.ids[stage.positions],
            stage.target, self.target_error, TARGET_FACTOR, self.geometry.shape)]

    def progress(self) -> Progress:
        """Counts for the current view (cheap: reads the sample counts once)."""
        vis = self.samples_at(self.visible) if len(self.visible) else np.zeros(0, np.uint32)
        surf = self.samples_at(self.surface) if len(self.surface) else np.zeros(0, np.uint32)
        stage = None
        if self._stage < len(self.stages):
            stage = (self.stages[self._stage].group, self.stages[self._stage].target)
        return Progress(
            visible=len(vis), visible_started=int((vis > 0).sum()),
            surface=len(surf), surface_started=int((surf > 0).sum()),
            visible_min_samples=int(vis.min()) if len(vis) else 0,
            stage=stage, iso=self.iso,
        )


# -- the loop a worker runs -----------------------------------------------------------------
@dataclass(frozen=True)
class View:
    """A message to the lazy baker: what is on screen.

    Attributes:
        iso: displayed isovalue.
        eye: (3,) world eye position.
        visible: (K,) flat base ids of the lattice cells under visible pixels, or None.
        light: (3,) unit vector towards the light the display turns (`turned_light`:
            the first directional light, else the sky's sun) as it shades it per pixel;
            None: no opinion (the bake keeps its light).
        points: (P, 3) float32 world surface points under the visible pixels, or None:
            previews start there, on the side the eye sees (`preview.seen_starts`).
    """

    iso: float
    eye: tuple[float, float, float]
    visible: np.ndarray | None = None
    light: tuple[float, float, float] | None = None
    points: np.ndarray | None = None


@dataclass
class ServeStats:
    """What the loop did: batches, paths, seconds tracing, per-message counters."""

    batches: int = 0
    paths: int = 0
    seconds: float = 0.0
    views: int = 0
    interrupted: int = 0
    started: float = field(default_factory=time.perf_counter)
    outside: View | None = None
    """The view that ended the loop because the plan does not serve it (`accepts`)."""


def serve(baker: Baker, scheduler: LazyScheduler, receive: Callable[[bool], object],
          send: Callable[[tuple], None], *, stop_when_done: bool = False,
          on_view: Callable[[View], None] | None = None,
          before_batch: Callable[[], bool] | None = None,
          accepts: Callable[[View], bool] | None = None) -> ServeStats:
    """Bake lazily until told to stop.

    Messages in (from `receive(block)`, which returns None when nothing is waiting and
    `block` is False): a `View` re-targets the work; ``"pause"``/``"resume"`` hold and
    release it; ``"stop"`` (or None while blocking: the sender is gone) ends the loop.

    Messages out (through `send`): ``("texels", flat_ids)`` after texels were committed to
    the lattice (the renderer re-uploads them), ``("progress", Progress, stats_dict)`` after
    every batch, every `REPORT_S` seconds within one, and when a view is done,
    ``("paused", bool)`` acknowledging a pause/resume (nothing is written to the lattice
    between a ``("paused", True)`` and the next resume).

    Args:
        baker: a `baking.bake.Baker` whose lattice the display reads.
        stop_when_done: return when the current view is finished (tests, benchmarks).
        on_view: called with each new `View` before the work is re-targeted (the viewer's
            first preview pass, `baking.preview`).
        before_batch: work that goes before each batch of the bake (the viewer's further preview
            passes); returns True when it did some, and the loop then reads its messages
            before going on.
        accepts: whether the baker's plan serves a view (its isovalue); a view it does not
            serve ends the loop, and is returned as `ServeStats.outside` (the caller
            plans again for it).
    """
    stats = ServeStats()
    paused = False
    ids = baker.plan.ids
    waiting: list = []  # messages that arrived during a batch

    last_report = 0.0

    def committed(positions: np.ndarray) -> None:
        send(("texels", ids[positions]))
        if time.perf_counter() - last_report > REPORT_S:  # a batch can take minutes
            report()
        message = receive(False)
        if message is not None:
            waiting.append(message)
            if message == "stop" or isinstance(message, View) or message == "pause":
                raise _Retarget  # Baker.run drops the unfinished pass of the batch

    def next_message(block: bool):
        return waiting.pop(0) if waiting else receive(block)

    def report() -> None:
        nonlocal last_report
        last_report = time.perf_counter()
        send(("progress", scheduler.progress(), _stats_dict(baker, stats)))

    def handle(message) -> bool:
        """Apply one message; False means stop."""
        nonlocal paused
        if message is None or message == "stop":
            return False
        if message in ("pause", "resume"):
            paused = message == "pause"
            send(("paused", paused))
        elif isinstance(message, View):
            if on_view is not None:
                on_view(message)
            scheduler.set_view(message.iso, np.asarray(message.eye), message.visible)
            stats.views += 1
            report()
        return True

    while True:
        waiting_now = []
        message = next_message(False)
        while message is not None:
            waiting_now.append(message)
            message = next_message(False)
        # control messages in order; of several views only the latest matters
        views = [m for m in waiting_now if isinstance(m, View)]
        for message in waiting_now:
            if not isinstance(message, View) and not handle(message):
                return stats
        if views and accepts is not None and not accepts(views[-1]):
            stats.outside = views[-1]
            return stats
        if views and not handle(views[-1]):
            return stats
        if not paused and before_batch is not None and before_batch():
            continue
        batch = None if paused or scheduler.iso is None else scheduler.next_batch()
        if batch is None:
            if scheduler.iso is not None and not paused:
                report()
                if stop_when_done:
                    return stats
            message = next_message(True)
            if isinstance(message, View) and accepts is not None and not accepts(message):
                stats.outside = message
                return stats
            if not handle(message):
                return stats
            continue
        t0 = time.perf_counter()
        before = int(baker.samples_done(batch.positions).sum())
        try:
            baker.run(batch.positions, batch.target, after_commit=committed)
        except _Retarget:
            stats.interrupted += 1
        stats.paths += int(baker.samples_done(batch.positions).sum()) - before
        stats.seconds += time.perf_counter() - t0
        stats.batches += 1
        report()


class _Retarget(KeyboardInterrupt):
    """Raised from `Baker.run`'s commit callback when a message needs the loop: the baker
    treats it as an interrupt (committed texels stay, the cut pass of the others is
    dropped whole), and `serve` picks up the message."""


def _stats_dict(baker: Baker, stats: ServeStats) -> dict:
    """JSON-ready counters for the progress display."""
    return {"batches": stats.batches, "paths": stats.paths, "seconds": stats.seconds,
            "interrupted": stats.interrupted,
            "rays": int(baker.stats.rays), "trace_seconds": float(baker.stats.trace_seconds),
            "scene_seconds": float(baker.stats.scene_seconds),
            "elapsed": time.perf_counter() - stats.started}
