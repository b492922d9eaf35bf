"""Isosurfaces for the viewer, extracted off the render thread.

`MeshWorker` (a thread) makes a coarse surface first (marching cubes every second to
fourth voxel: `preview_step`), then the full-resolution one. Marching cubes runs on every
core without the GIL (`volumes.isosurface`), so the render thread keeps its pace, and a
newer request cancels a stale extraction within its passes. Results for an isovalue the
user has already left are dropped.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from isolume import volumes

if TYPE_CHECKING:
    from isolume.app.viewer.draw import Drawing
    from isolume.app.viewer.state import ViewerState

COARSE_STEP = 2
"""Smallest marching-cubes step of the preview surface."""
LARGEST_STEP = 4
"""Largest marching-cubes step of the preview surface."""
PREVIEW_TARGET_TRIANGLES = 35_000
"""The preview's step grows (to at most `LARGEST_STEP`) so that it has about this many
triangles."""


def preview_step(full_triangles: int | None) -> int:
    """Marching-cubes step of the preview surface, given the full surface's triangle count
    (last time's, or `estimated_triangles`; triangles fall with the square of the step)."""
    if not full_triangles:
        return COARSE_STEP
    step = round(math.sqrt(full_triangles / PREVIEW_TARGET_TRIANGLES))
    return int(min(max(step, COARSE_STEP), LARGEST_STEP))


def estimated_triangles(coarsest: volumes.Mesh) -> int:
    """The full surface's triangle count estimated from the surface `coarsest` made at
    `LARGEST_STEP` (a smooth surface's triangles grow with the square of the resolution;
    a noisy one has more at full resolution, so the estimate errs on the finer preview)."""
    return len(coarsest.faces) * LARGEST_STEP ** 2


def extract_surface(volume: volumes.Volume, iso: float, *, step: int = 1,
                    normals: str = "smooth", flip: bool = False,
                    cancelled: Callable[[], bool] | None = None) -> volumes.Mesh | None:
    """The isosurface ρ = iso (`volumes.isosurface`, cancellable).

    Args:
        step: marching-cubes step in voxels.
        normals: "smooth" (cubic-B-spline gradient) or "gradient" (central differences).
        cancelled: asked during the marching cubes; True abandons the work (returns None).

    Returns:
        The mesh in world units (empty, with a message, when there is no surface), or
        None when cancelled.
    """
    lo, hi = volume.value_range
    if not lo < iso < hi:
        return volumes.Mesh.empty_at(iso, f"isovalue {iso:g} is at or beyond the data's "
                                     f"extremes [{lo:g}, {hi:g}]; nothing to show")
    return volumes.isosurface(volume, iso, normals=normals, flip_normals=flip, step_size=step,
                              cancelled=cancelled)


@dataclass(frozen=True)
class MeshResult:
    """A surface from the worker: request number, stage ("coarse", "full", or "lod": a
    lighter preview made after the full surface), seconds since the request."""

    request: int
    iso: float
    stage: str
    mesh: volumes.Mesh
    seconds: float


class MeshWorker:
    """Extracts isosurfaces on a background thread, coarse then full; a newer request
    cancels the older one as it runs, and `poll` returns results of the newest only."""

    volume: volumes.Volume
    normals: str
    flip: bool

    def __init__(self, volume: volumes.Volume, *, normals: str = "smooth",
                 flip: bool = False) -> None:
        self.volume, self.normals, self.flip = volume, normals, flip
        self.coarse: bool = min(volume.data.shape) >= 8 * COARSE_STEP
        self._cv = threading.Condition()
        self._pending: tuple[int, float, float] | None = None
        self._latest = 0
        self._results: list[MeshResult] = []
        self._closed = False
        self._full_triangles: int | None = None
        self.error: str | None = None
        self._thread = threading.Thread(target=self._loop, name="isolume-mesh", daemon=True)
        self._thread.start()

    def request(self, iso: float) -> int:
        """Ask for the surface at `iso`; returns the request number."""
        with self._cv:
            self._latest += 1
            self._pending = (self._latest, float(iso), time.perf_counter())
            self._cv.notify()
            return self._latest

    def poll(self) -> list[MeshResult]:
        """Results that arrived since the last call, for the newest request only."""
        with self._cv:
            out = [r for r in self._results if r.request == self._latest]
            self._results.clear()
        return out

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(timeout=5)

    def _stale(self, request: int) -> bool:
        return self._closed or request != self._latest

    def _loop(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                request, iso, t0 = self._pending
                self._pending = None
            try:
                self._extract(request, iso, t0)
            except Exception as exc:  # report, keep serving later requests
                self.error = f"surface extraction failed at iso {iso:g}: {exc}"

    def _stages(self, stages: list[tuple[str, int]]):
        """The planned stages, then ("lod", step) when the full surface turned out to want
        a coarser preview than the one made (the first time: its size was unknown)."""
        yield from stages
        if self.coarse and preview_step(self._full_triangles) > stages[0][1]:
            yield "lod", preview_step(self._full_triangles)

    def _extract(self, request: int, iso: float, t0: float) -> None:
        """The surfaces of one request, coarse (when the volume has one) then full. The
        first time, when the full surface's size is not known yet, the coarsest preview is
        made first: where its `estimated_triangles` want that step (a 512³ CT: 0.4 s for
        0.55 M triangles, drawn in ~1 s in software GL, where every second voxel takes
        1.7–3 s for 3 M, drawn in 1.6 s) it is the coarse surface, else the step they
        want is made."""
        extract = functools.partial(extract_surface, self.volume, iso, normals=self.normals,
                                    flip=self.flip, cancelled=lambda r=request: self._stale(r))
        coarsest = None  # made at LARGEST_STEP to estimate the full surface's size
        if self.coarse and self._full_triangles is None:
            coarsest = extract(step=LARGEST_STEP)
            if coarsest is None:
                return
            coarse = preview_step(estimated_triangles(coarsest))
        else:
            coarse = preview_step(self._full_triangles)
        stages = [("coarse", coarse), ("full", 1)] if self.coarse else [("full", 1)]
        for stage, step in self._stages(stages):
            reuse = stage == "coarse" and step == LARGEST_STEP and coarsest is not None
            mesh = coarsest if reuse else extract(step=step)
            if mesh is None:
                return
            if stage == "full":
                self._full_triangles = len(mesh.faces) or self._full_triangles
            with self._cv:
                if self._stale(request):
                    return
                self._results.append(MeshResult(request, iso, stage, mesh,
                                                time.perf_counter() - t0))


# -- the render thread's side -------------------------------------------------------------
@dataclass
class Extraction:
    """Figures of one isovalue change: seconds to the coarse and full surface, frames drawn
    meanwhile and the longest gap between frames (milliseconds); `requested` is the
    `time.perf_counter` of the request."""

    iso: float
    requested: float
    coarse_s: float | None = None
    full_s: float | None = None
    frames: int = 0
    max_gap_ms: float = 0.0
    triangles: int = 0


class SurfaceFeed:
    """What the render thread knows of the surfaces: it asks a `MeshWorker` for them and
    notes which one arrived last and the figures of every isovalue change.

    Attributes:
        worker: the extraction thread.
        stage: the stage ("coarse", "full") of the last surface received (None: none yet).
        iso: that surface's isovalue (None: none yet).
        info: the panel's line about it, e.g. "full resolution: 594,782 triangles, ...".
        extractions: one `Extraction` per request, the newest last.
    """

    def __init__(self, volume: volumes.Volume, *, normals: str = "smooth",
                 flip: bool = False) -> None:
        self.worker: MeshWorker = MeshWorker(volume, normals=normals, flip=flip)
        self.stage: str | None = None
        self.iso: float | None = None
        self.info: str = "extracting..."
        self.extractions: list[Extraction] = []

    def request(self, iso: float) -> None:
        """Ask for the surface at `iso` and start its `Extraction` record."""
        self.worker.request(iso)
        self.extractions.append(Extraction(iso, time.perf_counter()))

    def take_error(self) -> str | None:
        """The worker's last error, once (None: none)."""
        error, self.worker.error = self.worker.error, None
        return error

    def poll(self) -> list[MeshResult]:
        """Results that arrived since the last call (`MeshWorker.poll`)."""
        return self.worker.poll()

    def received(self, result: MeshResult) -> None:
        """Note a coarse or full surface that is now shown."""
        mesh = result.mesh
        self.stage, self.iso = result.stage, result.iso
        stage = "full resolution" if result.stage == "full" else "preview"
        self.info = (mesh.message if mesh.empty else
                     f"{stage}: {len(mesh.faces):,} triangles, {len(mesh.vertices):,} vertices")
        record = self.extractions[-1]
        if result.stage == "coarse":
            record.coarse_s = result.seconds
        else:
            record.full_s, record.triangles = result.seconds, len(mesh.faces)

    def stage_at(self, iso: float) -> str | None:
        """The stage of the surface shown when it is the one at `iso`, else None."""
        return self.stage if self.iso == iso else None

    def ready(self, iso: float) -> bool:
        """The full-resolution surface at `iso` is the one shown."""
        return self.stage == "full" and self.iso == iso

    @property
    def pending(self) -> bool:
        """The newest request's full surface has not arrived yet."""
        return bool(self.extractions) and self.extractions[-1].full_s is None

    def close(self) -> None:
        self.worker.close()


def hand_over(feed: SurfaceFeed, drawing: Drawing, state: ViewerState) -> bool:
    """Hand the surfaces that arrived from `feed` to `drawing` (an `app.viewer.draw.
    Drawing`: the lighter "lod" preview kept for moving the camera, the others shown and
    put on the GPU, the preview while `state`, an `app.viewer.state.ViewerState`, is
    interacting, and a redraw asked for); an extraction error becomes `state.message`.
    Returns whether a surface was shown."""
    error = feed.take_error()
    if error:
        state.message = error
    shown = False
    for result in feed.poll():
        if result.stage == "lod":  # a lighter preview for moving the camera
            if result.iso == feed.iso:
                drawing.meshes["coarse"] = result.mesh
            continue
        drawing.set_surface(result.stage, result.mesh, new_iso=result.iso != feed.iso)
        drawing.sync_mesh(preview=drawing.quality.coarse
                          and state.interacting(time.perf_counter()))
        feed.received(result)
        state.redraw()
        shown = True
    return shown
