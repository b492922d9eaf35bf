"""Preview passes for the lazy viewer: the picture on screen right within seconds.

A lattice texel's proper value needs paths on its *own* isosurface, and the texels around
one displayed surface span dozens of isovalue levels — one marching-cubes mesh and one
Embree scene each (`baking.plan`), seconds apiece on a CT scan, ~90 s for the engine's 64
levels. The displayed surface, however, is one scene, and for the picture on screen it is
the right one: the renderer interpolates these texels on exactly that surface. So before
(and besides) the level-by-level bake, the corner texels of the visible cells get paths
traced on the displayed isosurface, in passes of growing path counts (`PASSES`), each
texel from the visible point nearest it on the side the eye sees (`seen_starts`; a
surface seen from its high-value side — a sheet between two fluids, a solid cut open by
the volume's border — is lit where it is seen), else from its centre projected onto it:
a few paths on a coarse mesh within about a second (one each where a view has so many
texels that more would take longer: `FIRST_PASS_PATHS`), then more on the full one. They go
to ``Lattice.preview`` with their path count in ``Lattice.preview_paths`` and the start
normals in ``Lattice.preview_facing``; a display shows a preview while the texel has fewer
samples of its own (`Lattice.displayed`), so the picture never gets noisier when the
bake's first samples arrive. Previews are never saved.

Their error, measured on the engine CT at its default view against per-pixel path tracing
of the displayed surface (`isolume bench lazy`): RMS over visible pixels 11.5 % at 4
paths (step-2 mesh), 3.0 % at 64, 2.2 % at 256 — the lattice baked level by level shows
3.6 % at 64 paths per texel and 2.9 % at 128 (its level and interpolation error), after
90–110 s. What previews cannot do is serve another isovalue: each texel's own value stays
the bake's job.
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.baking import bin_kernels, kernels, octahedral, rng
from isolume.baking.bake import path_settings, tracing_lights
from isolume.baking.config import BakeConfig
from isolume.baking.integrator import whole_paths
from isolume.baking.lattice import TRAPPED_PATHS, Lattice, LatticeGeometry, sky_everywhere
from isolume.baking.lazy import corner_offsets, visible_cells
from isolume.baking.passes import Tracing
from isolume.baking.plan import grouped_by_bin, project_to_level
from isolume.baking.reference import primary_hits
from isolume.baking.view_paths import noise_placed, trace_counts
from isolume.volumes import cores

if TYPE_CHECKING:  # embreex is imported only when a preview traces
    from isolume.baking.trace import Scene

PASSES = ((4, True), (64, False), (256, False))
"""(paths per texel, coarse mesh allowed) of the preview passes of a view, in order; the
path counts are capped at the bake's `samples` (the previews give way to a finished
bake)."""
FIRST_PASS_PATHS = 1 << 19
"""Paths a view's first preview pass traces at most, when later passes follow: a view of
more texels than `PASSES`' first count allows gets fewer paths each, down to one (the
512³ foot CT's 493 k visible texels: one each, 0.7 s on 2 cores; the engine CT's 112 k
keep four)."""
COARSE_VOXELS = 1 << 22
"""Volumes with more voxels than this (e.g. 256×256×64) get a step-2 surface for the first
pass (4× fewer triangles, 4× faster to extract and to hand to Embree), those with more
than 8 times as many (e.g. 512×256×256) a step-4 one (as many cells across the surface as
step 2 at half the size: on the 512³ foot CT 0.4 s of marching cubes for 0.55 M
triangles, where step 2 takes 1.7–3 s for 3 M); smaller ones the full one. On a 32³
shells volume the step-2 mesh loses parts of the thin shells and the estimates come out
11 % too bright; at full detail they agree with the bake to 0.3 %."""
COARSE_OFFSET_VOXELS = 0.5
"""Start-point offset on a step-2 surface, voxels: a step-s mesh sits up to
(s voxels)²/(8 R) off the true surface in concave regions of radius R, so the bake's 0.25
voxels would let concave texels start behind a facet for R < 2 voxels; a step-s surface
offsets (s / 2)² times as far (`coarse_offset`)."""
REACH_VOXELS = 2.0
"""Largest move of a texel centre onto the displayed surface (smoothed-field steps)."""
FINISH_VOXELS = 0.5
"""Largest further move onto the raw field's surface (plain steps)."""
PATHS_PER_STEP = 1 << 17
"""Paths traced per `Previewer.step` (~0.15 s on 2 cores, idle): the bake process reads
its messages between steps, so a new view waits about that long for its first pass."""
SEED_SALT = 0x5EED_F1A5
"""Mixed into the bake seed: previews use paths of their own."""


def cell_corners(shape: tuple[int, int, int], cells: np.ndarray) -> np.ndarray:
    """(K,) sorted unique flat ids of the 8 corner texels of (N,) cells given by the flat
    id of their (0, 0, 0) corner."""
    flat = (np.asarray(cells, np.int64)[:, None] + corner_offsets(shape)[None, :]).reshape(-1)
    return np.unique(flat[flat < int(np.prod(shape))])


def picture_texels(geometry: LatticeGeometry, points: np.ndarray) -> np.ndarray:
    """(K,) sorted flat ids of the texels a picture reads: the corners of the lattice
    cells under its (N, 3) visible surface points (`baking.lazy.visible_cells`)."""
    return cell_corners(geometry.shape, visible_cells(geometry, points))


def mesh_step(volume: volumes.Volume, coarse: bool) -> int:
    """Marching-cubes step of a preview surface: where `coarse` is allowed, 2 for a volume
    above `COARSE_VOXELS` and 4 above 8 times that; else 1."""
    if not coarse or volume.data.size <= COARSE_VOXELS:
        return 1
    return 2 if volume.data.size <= 8 * COARSE_VOXELS else 4


def coarse_offset(step: int) -> float:
    """Start-point offset of paths from a preview surface of marching-cubes `step` > 1,
    voxels (`COARSE_OFFSET_VOXELS`)."""
    return COARSE_OFFSET_VOXELS * (step / 2) ** 2


def surface_scene(volume: volumes.Volume, iso: float, step: int) -> Scene | None:
    """Embree scene of the isosurface ρ = `iso` extracted with `step`, or None when it is
    empty."""
    from isolume.baking.trace import Scene

    mesh = volumes.isosurface(volume, iso, step_size=step, normals="none")
    return None if mesh.empty else Scene(mesh.vertices, mesh.faces)


def estimate(volume: volumes.Volume, config: BakeConfig, lattice: Lattice, iso: float,
             flat: np.ndarray, scene: Scene, step: int, *, paths: int, tracing: Tracing,
             workers: int = 1, seen: SeenSurface | None = None,
             told: Callable[[int], None] | None = None, share: np.ndarray | None = None
             ) -> None:
    """Trace `paths` paths from each texel `flat` (K,) and store the means as the texels'
    previews (`store_preview` of a `Lattice` whose ``preview`` and ``preview_paths`` are
    set, or of a `baking.view_texels.HeldLattice` holding the texels) for the surface
    ρ = `iso` (whose `scene` has the given marching-cubes `step`); `tracing` is
    `preview_tracing` (volume, config). With the (K,) `share` of a picture each texel has
    (`baking.view_paths.picture_share`), `paths` a texel on average, placed where the
    picture's noise is (`baking.view_paths.noise_placed`).

    With `seen` (the surface the view shows), each texel starts from the visible point
    nearest it among those whose lookups read it (`seen_starts`): on the side of the
    surface the eye sees, which is where the picture shows the light. Texels no visible
    point reads, and every texel without `seen`, start from their centres projected onto
    the surface (`projected_starts`).

    `told(done)`, where given, is told how many of the texels are traced (with a `share`,
    the texels' worth of the budget traced), as the calling thread's work items end
    (rising, ending at K): one call traces many texels on every core, with no barrier
    between reports.
    """
    origins = np.zeros((len(flat), 3))
    normals = np.zeros((len(flat), 3))
    usable = np.zeros(len(flat), bool)
    if seen is not None:
        found = seen_starts(flat, seen)
        has = found >= 0
        origins[has], normals[has] = seen.origins[found[has]], seen.normals[found[has]]
        usable[has] = True
    rest = ~usable
    if rest.any():
        o, n, ok = projected_starts(volume, config, lattice, iso, flat[rest], step)
        origins[rest], normals[rest], usable[rest] = o, n, ok
    means, codes = np.zeros((0, lattice.values.shape[-1])), np.zeros((0, 2), np.uint8)
    counts = np.zeros(len(flat), np.int64)
    if usable.any():
        skipped = len(flat) - int(np.count_nonzero(usable))
        traced = dataclasses.replace(tracing, ids=np.asarray(flat[usable], np.int64))
        starts = (origins[usable].astype(np.float32), normals[usable].astype(np.float32))
        progress = None if told is None else lambda done: told(skipped + done)
        if share is None:
            count = np.full(len(traced.ids), paths, np.int64)
            sums = trace_counts(scene, traced, *starts, np.zeros_like(count), count, workers,
                                progress).sum
        else:
            sums, count = noise_placed(scene, traced, *starts, lattice.geometry.shape,
                                       share[usable], paths,
                                       TRAPPED_PATHS if sky_everywhere(config) else 0,
                                       workers, progress)
        means, codes = sums / count[:, None], octahedral.encode(normals[usable])
        counts[usable] = count
    lattice.store_preview(flat, counts, means, codes)
    if told is not None:
        told(len(flat))


def projected_starts(volume: volumes.Volume, config: BakeConfig, lattice: Lattice,
                     iso: float, flat: np.ndarray, step: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start points of texels `flat` (K,) on the surface ρ = `iso` found from their centres.

    The centres move onto the surface (up to 2 voxels) by Newton steps along the smoothed
    gradient, then along the plain one, which lands them on the raw field's surface that
    the mesh shows; they start from there along the bake's (smoothed) normal. Measured on
    the engine CT's 112 k visible texels at 64 paths against per-pixel path tracing:
    plain steps and normals 3.2 % (and black marks on the synthetic engine's thin posts),
    smoothed steps and normals 4.2 % (593 texels stalled short of the surface, inside the
    material: black), both in turn 3.0 % (none). A step-2 surface (the first pass on large
    volumes) takes plain steps and normals (no smoothed grid to wait for) and a larger
    offset.

    Returns:
        (K, 3) origins and (K, 3) unit normals, world units, and (K,) bool: the start lies
        outside the material (`_outside`); the others must not be traced.
    """
    h = float(np.mean(volume.spacing))
    smooth = step == 1 and config.normals == "smooth"
    on_surface = project_to_level(volume, lattice.geometry.centres(flat), iso,
                                  max_move=REACH_VOXELS * h, smooth=smooth)
    if smooth:  # finish on the raw field's surface
        on_surface = project_to_level(volume, on_surface, iso, max_move=FINISH_VOXELS * h,
                                      smooth=False)
    normals = volumes.normals_at(volume, on_surface, smooth=smooth, flip=config.flip_normals)
    offset = coarse_offset(step) if step > 1 else config.offset
    origins = on_surface + offset * h * normals
    return origins, normals, _outside(volume, origins, iso, config.flip_normals)


@dataclass(frozen=True)
class SeenSurface:
    """The surface points a view shows, the start points of paths there, and the point
    each texel starts from.

    Attributes:
        points: (M, 3) world hit points of the eye's rays on the displayed surface.
        origins: (M, 3) path start points off them, on the side the eye sees (checked:
            `reference.clear_starts`).
        normals: (M, 3) unit normals turned to the side the eye sees.
        texels: (T,) sorted flat ids of the texels the points' trilinear lookups read.
        nearest: (T,) index of the point nearest each of `texels` among those reading it.
    """

    points: np.ndarray
    origins: np.ndarray
    normals: np.ndarray
    texels: np.ndarray
    nearest: np.ndarray


def seen_surface(scene: Scene, volume: volumes.Volume, config: BakeConfig,
                 geometry: LatticeGeometry, eye: np.ndarray, points: np.ndarray
                 ) -> SeenSurface:
    """The visible surface of a view: rays from `eye` (3,) through the (N, 3) world
    `points` a picture shows (its position pass), traced against `scene` and started as
    `isolume reference` starts its pixels (`reference.primary_hits`), with the nearest
    point of each texel of `geometry` they read (`nearest_points`)."""
    dirs, usable = _eye_directions(np.asarray(points), np.asarray(eye, np.float64))
    dirs = dirs[usable]  # (Embree needs finite, non-zero rays)
    origins = np.broadcast_to(np.asarray(eye, np.float64), dirs.shape)
    hits = primary_hits(scene, volume, origins, dirs, config,
                        smooth=config.normals == "smooth")
    texels, nearest = nearest_points(geometry, hits.points)
    return SeenSurface(hits.points, hits.origins, hits.normals, texels, nearest)


def _eye_directions(points: np.ndarray, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) unit directions from (3,) `eye` to (N, 3) `points`, and (N,) whether each
    is usable (finite, of non-zero length), in blocks on every core."""
    dirs, usable = np.empty((len(points), 3)), np.empty(len(points), bool)

    def block(part: slice) -> None:
        towards = np.asarray(points[part], np.float64) - eye[None, :]
        length = np.linalg.norm(towards, axis=1)
        usable[part] = np.isfinite(length) & (length > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            dirs[part] = towards / length[:, None]

    cores.for_blocks(block, len(points), EYE_BLOCK, "primary rays")
    return dirs, usable


EYE_BLOCK = 1 << 16
"""Points `_eye_directions` takes in one work item."""
NEAREST_BINS = 1024
"""Most bins of consecutive texel ids `nearest_points` groups the corners it reads into."""


def nearest_points(geometry: LatticeGeometry, points: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(T,) sorted flat ids of the texels that trilinear lookups at (M, 3) world `points`
    read, and (T,) the index of the point nearest each (world distance to its centre; the
    first such point on ties).

    On every core: each point's 8 corners and their distances
    (`bin_kernels.corner_reads`), the corners grouped into bins of consecutive texel ids
    by a counting sort (`plan.grouped_by_bin`), each bin's texels and their nearest points
    found in it (`bin_kernels.nearest_in_bins`), and packed (`bin_kernels.gather_bins`) —
    what a sort of all corners by texel and distance gives, without the sort."""
    if len(points) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    coords = np.ascontiguousarray(geometry.to_texel_coords(points))  # (M, 3) z, y, x
    shape = np.asarray(geometry.shape, np.int64)
    size = np.asarray(geometry.texel_size[::-1], np.float64)  # z, y, x
    scale = 2.0 * float((size**2).sum()) + 1e-30
    corners = 8 * len(coords)
    read, close = np.empty(corners, np.int64), np.empty(corners, np.float64)
    cores.for_ranges(lambda lo, hi: bin_kernels.corner_reads(coords, shape, size, scale,
                                                             lo, hi, read, close),
                     len(coords), 8, "nearest points")
    texels = int(np.prod(shape))
    bits = max(0, (texels - 1).bit_length() - NEAREST_BINS.bit_length() + 1)
    entries, counts = grouped_by_bin(read, None, ((texels - 1) >> bits) + 1,
                                     "nearest points", shift=bits)
    starts = np.concatenate([[0], np.cumsum(counts)])
    bounds = [int(np.searchsorted(starts, lo)) for lo, _ in cores.item_bounds(corners, 1)]
    bounds = sorted({*bounds, len(counts)})
    texel, point = entries, np.empty(corners, np.int64)  # texels over the entries read
    held = np.empty(len(counts), np.int64)
    cores.for_items(lambda i: bin_kernels.nearest_in_bins(read, close, entries, starts,
                                                          bounds[i], bounds[i + 1], bits,
                                                          texel, point, held),
                    len(bounds) - 1, "nearest points")
    places = np.concatenate([[0], np.cumsum(held)])
    texels, nearest = np.empty(places[-1], np.int64), np.empty(places[-1], np.int64)
    cores.for_items(lambda i: bin_kernels.gather_bins(texel, point, starts, held, places,
                                                      bounds[i], bounds[i + 1], texels,
                                                      nearest),
                    len(bounds) - 1, "nearest points")
    return texels, nearest


def seen_starts(flat: np.ndarray, seen: SeenSurface) -> np.ndarray:
    """(K,) index into `seen` of the visible point nearest each texel `flat` (K,) among
    the points whose trilinear lookups read it; -1 where none does."""
    if len(seen.texels) == 0 or len(flat) == 0:
        return np.full(len(flat), -1, np.int64)
    at = np.minimum(np.searchsorted(seen.texels, flat), len(seen.texels) - 1)
    return np.where(seen.texels[at] == flat, seen.nearest[at], -1)


def _outside(volume: volumes.Volume, origins: np.ndarray, iso: float, flip: bool) -> np.ndarray:
    """(N,) bool: the start points lie on the side of ρ = iso that the normals point to
    (lower values, higher if `flip`). Elsewhere — a thin feature whose two faces the
    smoothed gradient blurs into one direction, a Newton path that ended across it — the
    paths would start inside the material and come back black: such texels get no
    preview, and the display interpolates their neighbours instead."""
    rho = volumes.value_at(volume, origins)
    return rho >= iso if flip else rho <= iso


def first_pass_paths(paths: int, texels: int) -> int:
    """Paths per texel of a first preview pass of `paths` paths over `texels` texels: as
    many as `FIRST_PASS_PATHS` allows, between 1 and `paths`."""
    return int(np.clip(FIRST_PASS_PATHS // max(texels, 1), 1, paths))


def pass_plan(samples: int) -> list[tuple[int, bool]]:
    """(paths, coarse mesh allowed) of the preview passes for a bake of `samples` paths
    per texel: `PASSES` with the path counts capped at `samples`."""
    top = min(samples, PASSES[-1][0])
    passes = [(paths, coarse) for paths, coarse in PASSES if paths < top]
    return [*passes, (top, not passes)]


class Previewer:
    """The preview passes of the view on screen, done a step at a time.

    `set_view` runs the first pass whole (a few paths per visible texel, about a second on
    a CT scan) and queues the others; `step` does the next slice of them. A pass skips the
    texels whose own samples already match it and those previewed for the same isovalue
    with as many paths.

    Args:
        lattice: the lattice the display reads (``preview`` and ``preview_paths`` set).
        workers: threads tracing concurrently.
    """

    def __init__(self, volume: volumes.Volume, config: BakeConfig, lattice: Lattice,
                 workers: int = 1) -> None:
        self.volume: volumes.Volume = volume
        self.config: BakeConfig = config
        self.lattice: Lattice = lattice
        self.workers: int = workers
        # set once the plan is known: the bake never replaces previews of inactive texels
        self.only_active: bool = False
        self.passes: list[tuple[int, bool]] = pass_plan(config.samples)
        self.iso: float | None = None
        self.done: list[dict[str, Any]] = []  # per finished pass: iso, paths, texels, seconds
        self._iso_of = np.full(lattice.samples.size, np.nan, np.float32)  # of each preview
        self._corners = np.zeros(0, np.int64)
        self._queue: list[list] = []  # [paths, coarse, texels still to do or None]
        self._scenes: dict[int, Scene | None] = {}  # by marching-cubes step
        self._view: tuple[np.ndarray, np.ndarray] | None = None  # eye, visible points
        self._seen: SeenSurface | None = None  # of `_view`, once traced
        self._started, self._pass_texels = 0.0, 0  # of the pass under way
        self._tracing = preview_tracing(volume, config)

    @property
    def busy(self) -> bool:
        """Preview work is waiting for `step`."""
        return bool(self._queue)

    @property
    def next_paths(self) -> int | None:
        """Paths per texel of the pass `step` works on next (None: idle)."""
        return self._queue[0][0] if self._queue else None

    def set_view(self, iso: float, cells: np.ndarray, eye: np.ndarray | None = None,
                 points: np.ndarray | None = None) -> np.ndarray:
        """A new view (isovalue, (N,) flat base ids of the visible cells): run its first
        pass and queue the others. With the `eye` (3,) and the (P, 3) world `points` the
        view shows, full-mesh passes start texels on the side the eye sees
        (`seen_starts`).

        Returns:
            (K,) flat ids of the texels whose previews changed.
        """
        if iso != self.iso:
            self._scenes.clear()
        self.iso = float(iso)
        self._view, self._seen = (None, None) if points is None or eye is None else (
            (np.asarray(eye, np.float64), np.asarray(points, np.float64)), None)
        self._corners = cell_corners(self.lattice.geometry.shape, cells)
        self._queue = [[paths, coarse, None] for paths, coarse in self.passes]
        if len(self._queue) > 1:
            self._queue[0][0] = first_pass_paths(self._queue[0][0], len(self._corners))
        return self.step(whole=True)

    def prepare(self, iso: float) -> None:
        """Build the surface scene a first pass at isovalue `iso` traces, ahead of the view
        (the bake process does it for the viewer's first isovalue while the window opens:
        on the 512³ foot CT that is 3 to 4 seconds of marching cubes and BVH)."""
        if iso != self.iso:
            self._scenes.clear()
        self.iso = float(iso)
        self._scene(mesh_step(self.volume, self.passes[0][1]))

    def step(self, whole: bool = False) -> np.ndarray:
        """Do the next slice (`PATHS_PER_STEP` paths; the rest of the pass if `whole`) of
        the queued passes.

        Returns:
            (K,) flat ids of the texels whose previews changed (empty when idle).
        """
        if not self._queue:
            return np.zeros(0, np.int64)
        paths, coarse, todo = self._queue[0]
        if todo is None:
            todo = self._todo(paths, mesh_step(self.volume, coarse))
            self._started, self._pass_texels = time.perf_counter(), len(todo)
        take = len(todo) if whole else max(1, PATHS_PER_STEP // paths)
        flat, self._queue[0][2] = todo[:take], todo[take:]
        if len(flat):
            step = mesh_step(self.volume, coarse)
            scene = self._scene(step)
            if scene is None:  # no surface at this isovalue
                self._queue.clear()
                return flat[:0]
            estimate(self.volume, self.config, self.lattice, self.iso, flat, scene, step,
                     paths=paths, tracing=self._tracing, workers=self.workers,
                     seen=self._seen_surface(scene) if step == 1 else None)
            self._iso_of[flat] = self.iso
        if take >= len(todo):
            self._queue.pop(0)
            self.done.append({"iso": self.iso, "paths": paths, "texels": self._pass_texels,
                              "seconds": time.perf_counter() - self._started})
        return flat

    def _todo(self, paths: int, step: int) -> np.ndarray:
        """Visible corner texels a pass of `paths` paths on the mesh of marching-cubes
        `step` still has to preview: all but those previewed for the same isovalue with as
        many paths, on the side this view sees (`_seen_other_side`)."""
        flat = self._corners[self.lattice.samples.reshape(-1)[self._corners] < paths]
        if self.only_active:
            flat = flat[self.lattice.active.reshape(-1)[flat]]
        fresh = (self._iso_of[flat] == np.float32(self.iso)) & (
            self.lattice.preview_paths.reshape(-1)[flat] >= paths)
        if step == 1 and fresh.any():
            fresh[fresh] = ~self._seen_other_side(flat[fresh])
        return flat[~fresh]

    def _seen_other_side(self, flat: np.ndarray) -> np.ndarray:
        """(K,) bool: the view sees the previews of texels `flat` (K,) from the side
        opposite the one they were lit on (a sheet or a thin wall orbited round)."""
        if self._view is None or self.lattice.preview_facing is None:
            return np.zeros(len(flat), bool)
        seen = self._seen_surface(self._scene(1))
        found = seen_starts(flat, seen)
        lit = octahedral.decode(self.lattice.preview_facing.reshape(-1, 2)[flat])
        turned = np.zeros(len(flat), bool)
        has = found >= 0
        turned[has] = (lit[has] * seen.normals[found[has]]).sum(axis=1) < 0
        return turned

    def _seen_surface(self, scene) -> SeenSurface | None:
        """The view's visible surface on the full-mesh `scene`, found once per view."""
        if self._seen is None and self._view is not None:
            self._seen = seen_surface(scene, self.volume, self.config,
                                      self.lattice.geometry, *self._view)
        return self._seen

    def _scene(self, step: int) -> Scene | None:
        """The displayed surface's scene at marching-cubes `step`, made once per isovalue."""
        if step not in self._scenes:
            self._scenes[step] = surface_scene(self.volume, self.iso, step)
        return self._scenes[step]


def preview_tracing(volume: volumes.Volume, config: BakeConfig) -> Tracing:
    """What the previews trace with (lighting parsed once: an HDR map is read and its
    sampler built here, not at every preview step); `estimate` fills in the texels and
    their sums. Previews take their own random numbers (`SEED_SALT`), their first
    directions stratified over each texel's samples (`Tracing.stratified`)."""
    lighting, settings = tracing_lights(config), path_settings(volume, config)
    return Tracing(np.zeros(0, np.int64), lighting, settings,
                   np.uint32(rng.seed_key(config.seed ^ SEED_SALT)),
                   np.zeros(settings.channels), whole_paths(lighting, settings),
                   stratified=True)


def drop_inactive(lattice: Lattice) -> np.ndarray:
    """Withdraw the previews of texels outside ``lattice.active`` (made before the plan
    was known); returns their (K,) flat ids, to be re-uploaded."""
    paths = lattice.preview_paths.reshape(-1)
    stale = np.flatnonzero((paths > 0) & ~lattice.active.reshape(-1))
    paths[stale] = 0
    return stale


def warm_up(volume: volumes.Volume) -> None:
    """Do ahead of the first view what the first preview pass would otherwise do on it: load
    the compiled kernels, the projection's among them (~1 s)."""
    kernels.warm_up()
    centre = np.mean(volume.sample_box, axis=0)[None, :]
    project_to_level(volume, centre, float(volume.data.mean()), 0.0, smooth=False)
