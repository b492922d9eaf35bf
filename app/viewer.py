"""``isolume view``: the interactive viewer.

One render thread owns the window, the GL context and the UI; the slow work happens
elsewhere so that the window never freezes:

* **Isosurfaces** (`MeshWorker`, a thread): a coarse surface (marching cubes every other
  voxel) first, then the full-resolution one. Marching cubes runs in z-slabs of about half
  a million voxels: scikit-image holds the GIL for a whole call (≈ 0.4 s on a 256²×128
  volume), slabs bound that to ≈ 25 ms, skip slabs whose values miss the isovalue, and let
  a newer request cancel a stale extraction between slabs. Results for an isovalue the user
  has already left are dropped.
* **Global illumination** (`BakeLink`, a separate process): the lazy baker of
  `baking.lazy` bakes the texels around the displayed isosurface, visible ones and those
  nearest the eye first, a few paths each, then refines. A process rather than a thread:
  building level scenes (marching cubes again) and the baker's own numpy work hold the GIL
  for hundreds of milliseconds. The lattice arrays live in shared memory: the baker writes
  texels, the viewer re-uploads the 8³ bricks that hold new texels (`TexelUploader`) within
  a per-frame budget. Texels not computed yet fall back to local shading (tinted).

Input goes to the UI first (Dear ImGui, `app.ui`) and to the camera only when the UI does
not want it. ``--script`` drives the same actions without a person (`app.viewer_script`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

import volumes

HELP = "open the interactive viewer (live isovalue, light, lazy global illumination)"

SLAB_VOXELS = 1 << 19
"""Voxels per marching-cubes call (a GIL hold of ~25 ms on one core)."""
COARSE_STEP = 2
"""Smallest marching-cubes step of the preview surface."""
PREVIEW_TARGET_TRIANGLES = 35_000
"""The preview's step grows (to at most 4) so that it has about this many triangles."""
BRICK = 8
"""Texels per side of the blocks re-uploaded after the bake commits texels."""
UPLOAD_BUDGET_S = 0.006
"""Seconds per frame spent re-uploading texels (the rest waits for the next frame)."""
SETTLE_S = 0.2
"""The view must be still this long before the visible texels are measured again."""
ISO_STEPS = 1000
"""A fine isovalue step is 1/ISO_STEPS of the data range (shift: ×10)."""
DEFAULT_BAKE_SAMPLES = 256
"""Paths per texel a new lazy lattice is refined up to (rounds of 4, 16, 64, 256)."""
INTERACTIVE_MS = 33.0
"""Frame time aimed at while the camera or light moves (≈ 30 fps)."""
RENDER_SCALES = (1.0, 0.75, 0.5, 0.35)
"""Resolution factors tried, in order, while interacting and too slow."""
PREVIEW_TRIANGLES = 60_000
"""While interacting and too slow, the preview surface replaces a full one above this."""


# -- command line -------------------------------------------------------------------------
def add_arguments(parser) -> None:
    """Options of ``isolume view``."""
    from .cli import _add_volume_options

    _add_volume_options(parser, optional=True)
    parser.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    parser.add_argument("--lattice", metavar="FILE",
                        help="illumination lattice: shown and, if incomplete, baked further "
                        "lazily; a new file is created; saved on exit and with S")
    parser.add_argument("--shading", default=None,
                        help="initial shading mode (default: irradiance when a lattice is "
                        "shown or baked, else phong_hemi)")
    parser.add_argument("--size", default="1024x768", help="window size WxH (screen units)")
    parser.add_argument("--exposure", type=float, default=1.0, help="linear exposure")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="render N frames once the surface is ready (after --script), "
                        "then exit")
    parser.add_argument("--screenshot", metavar="FILE",
                        help="on exit write FILE.png (sRGB) and FILE.exr (linear radiance)")
    parser.add_argument("--script", metavar="FILE",
                        help="commands, one per line: iso V | orbit DAZ DEL | zoom F | "
                        "pan DX DY | reset | mode NAME | light AZ EL | light camera | "
                        "exposure X | wait-mesh [T] | wait-bake FRACTION [T] | frames N | "
                        "sleep S | screenshot FILE | window-shot FILE | save-lattice [FILE] "
                        "| check-lattice | quit")
    parser.add_argument("--stats", metavar="FILE.json",
                        help="write frame times, extraction and bake figures on exit")
    parser.add_argument("--no-bake", action="store_true",
                        help="no lazy global illumination (local shading, or --lattice as is)")
    parser.add_argument("--bake-mode", default="irradiance", choices=["irradiance", "sh"],
                        help="what a new lazy lattice holds: irradiance (fixed light) or SH "
                        "transfer (the environment rotates with the light controls)")
    parser.add_argument("--bake-env", default="constant:1,1,1",
                        help="environment of a new lazy lattice: constant:R,G,B | sky[:...] | "
                        "FILE.exr/.hdr (as isolume bake --env)")
    parser.add_argument("--bake-samples", type=int, default=DEFAULT_BAKE_SAMPLES,
                        help="paths per texel the lazy bake refines up to (new lattices)")
    parser.add_argument("--bake-workers", type=int, default=None,
                        help="tracing threads of the lazy bake (default: all cores)")
    parser.add_argument("--bake-max-levels", type=int, default=64, metavar="K",
                        help="isovalue levels of a new lazy lattice (fewer: the first sweep "
                        "builds fewer scenes and converges sooner, texels move farther "
                        "onto their levels and a few come out wrong; default 64)")
    parser.add_argument("--no-ui", action="store_true", help="no control panel")
    parser.add_argument("--normals", default="smooth", choices=["smooth", "gradient"])
    parser.add_argument("--flip-normals", action="store_true",
                        help="material less dense than air")


@dataclass(frozen=True)
class Options:
    """Validated viewer options (everything checked before a window opens)."""

    size: tuple[int, int]
    shading: str | None
    exposure: float
    frames: int | None
    screenshot: Path | None
    script: tuple
    stats: Path | None
    bake: bool
    bake_mode: str
    bake_env: str
    bake_samples: int
    bake_workers: int | None
    bake_max_levels: int
    ui: bool
    normals: str
    flip_normals: bool
    lattice_path: Path | None


def _options(args) -> Options:
    """Check the command line; raise `app.cli.CLIError` with one-line messages."""
    from .cli import CLIError, _size
    from .images import check_output_path
    from .render import SHADING_MODES
    from .viewer_script import load_script

    if args.shading is not None and args.shading not in SHADING_MODES:
        raise CLIError(f"--shading {args.shading!r}: expected one of {', '.join(SHADING_MODES)}")
    if not args.exposure > 0:
        raise CLIError(f"--exposure {args.exposure:g}: must be positive")
    if args.frames is not None and args.frames < 1:
        raise CLIError(f"--frames {args.frames}: expected at least 1")
    if args.bake_samples < 1:
        raise CLIError(f"--bake-samples {args.bake_samples}: expected at least 1")
    if args.bake_workers is not None and args.bake_workers < 1:
        raise CLIError(f"--bake-workers {args.bake_workers}: expected at least 1")
    if not 2 <= args.bake_max_levels <= 1024:
        raise CLIError(f"--bake-max-levels {args.bake_max_levels}: expected 2 to 1024")
    if not args.no_bake:
        from baking.environment import parse_env

        parse_env(args.bake_env)  # EnvSpecError (a one-line user error) before any window
    screenshot = check_output_path(args.screenshot) if args.screenshot else None
    stats = check_output_path(args.stats, (".json",)) if args.stats else None
    lattice = check_output_path(args.lattice, (".npz",)) if args.lattice else None
    script = tuple(load_script(args.script, SHADING_MODES)) if args.script else ()
    return Options(
        size=_size(args.size), shading=args.shading, exposure=args.exposure,
        frames=args.frames, screenshot=screenshot, script=script, stats=stats,
        bake=not args.no_bake, bake_mode=args.bake_mode, bake_env=args.bake_env,
        bake_samples=args.bake_samples, bake_workers=args.bake_workers,
        bake_max_levels=args.bake_max_levels, ui=not args.no_ui, normals=args.normals,
        flip_normals=args.flip_normals, lattice_path=lattice,
    )


def run(args) -> int:
    """Entry point of ``isolume view``: bad input ends in one line on stderr, status 2.

    (The errors are reported here rather than by `app.cli.main`: under ``python -m app.cli``
    that module runs as ``__main__`` and its `CLIError` is not the one this module sees.)
    """
    from .cli import EXIT_USER_ERROR, CLIError
    from .viewer_script import ScriptError

    try:
        return _run(args)
    except (CLIError, ScriptError, ViewerError) as exc:
        print(f"isolume: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USER_ERROR


def _run(args) -> int:
    from .cli import _isovalue, _load_volume

    options = _options(args)
    volume = _load_volume(args)
    iso = _isovalue(volume, args.iso)
    lattice = None
    if options.lattice_path is not None and options.lattice_path.exists():
        from baking.lattice import Lattice

        lattice = Lattice.load(options.lattice_path, volume)
    from .render import LATTICE_MODES

    if options.shading in LATTICE_MODES and lattice is None and not options.bake:
        raise ViewerError(f"--shading {options.shading} needs a lattice: pass --lattice FILE, or "
                       "leave out --no-bake to bake one lazily")

    viewer = Viewer(volume, iso, lattice, options)
    try:
        return viewer.run()
    except KeyboardInterrupt:
        return 130
    finally:
        viewer.close()


# -- isosurfaces off the render thread ----------------------------------------------------
def mesh_normals(vertices: np.ndarray, faces: np.ndarray, flip: bool = False) -> np.ndarray:
    """(V, 3) float32 unit vertex normals from area-weighted face normals of a marching-cubes
    mesh in world units (they point from high to low values like the field's; `flip`
    reverses them). Cheap: used for previews before the smoothed gradient is ready."""
    p = vertices.astype(np.float64)[faces]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    idx = faces.reshape(-1)
    vn = np.stack([np.bincount(idx, np.repeat(fn[:, c], 3), minlength=len(vertices))
                   for c in range(3)], axis=1)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
    return (-vn if flip else vn).astype(np.float32)


def preview_step(full_triangles: int | None) -> int:
    """Marching-cubes step of the preview surface, given the full surface's triangle count
    last time (triangles fall with the square of the step)."""
    if not full_triangles:
        return COARSE_STEP
    step = round(math.sqrt(full_triangles / PREVIEW_TARGET_TRIANGLES))
    return int(min(max(step, COARSE_STEP), 4))


def extract_surface(volume: volumes.Volume, iso: float, *, step: int = 1,
                    normals: str = "smooth", flip: bool = False,
                    cancelled=None) -> volumes.Mesh | None:
    """The isosurface ρ = iso by marching cubes in z-slabs (see the module docstring).

    The triangles are those of `volumes.isosurface` at the same step (vertices on slab
    boundaries appear once per slab; they coincide, so nothing shows).

    Args:
        step: marching-cubes step in voxels.
        normals: "smooth" (cubic-B-spline gradient, as `volumes.isosurface`), "gradient"
            (central differences) or "mesh" (from the triangles, cheapest).
        cancelled: called between slabs; True abandons the work (returns None).

    Returns:
        The mesh in world units (empty, with a message, when there is no surface), or
        None when cancelled.
    """
    from skimage import measure

    lo, hi = volume.value_range
    if not lo < iso < hi:
        return volumes.Mesh.empty_at(iso, f"isovalue {iso:g} is at or beyond the data's "
                                     f"extremes [{lo:g}, {hi:g}]; nothing to show")
    data = volume.data
    nz, ny, nx = data.shape
    thick = max(step, (SLAB_VOXELS // (ny * nx)) // step * step)
    parts_v, parts_f, count = [], [], 0
    for z0 in range(0, nz - 1, thick):
        if cancelled is not None and cancelled():
            return None
        block = data[z0:min(z0 + thick, nz - 1) + 1]
        if block.min() > iso or block.max() < iso:
            continue
        try:
            v, f, _, _ = measure.marching_cubes(block, level=iso, step_size=step,
                                                allow_degenerate=False)
        except (ValueError, RuntimeError):  # a slab thinner than the step, or no crossing
            continue
        v[:, 0] += z0
        parts_v.append(v)
        parts_f.append(f + count)
        count += len(v)
    if not parts_f:
        return volumes.Mesh.empty_at(iso, f"no surface at isovalue {iso:g}")
    world = volume.index_to_world(np.concatenate(parts_v)).astype(np.float32)
    faces = np.concatenate(parts_f).astype(np.uint32)
    if normals == "mesh":
        n = mesh_normals(world, faces, flip)
    else:
        n = volumes.normals_at(volume, world, smooth=normals == "smooth", flip=flip)
    return volumes.Mesh(world, faces, n, iso)


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
    cancels the older one between slabs, and `poll` returns results of the newest only."""

    def __init__(self, volume: volumes.Volume, *, normals: str = "smooth",
                 flip: bool = False) -> None:
        self.volume, self.normals, self.flip = volume, normals, flip
        self.coarse = min(volume.data.shape) >= 8 * COARSE_STEP
        self._cv = threading.Condition()
        self._pending: tuple[int, float, float] | None = None
        self._latest = 0
        self._results: list[MeshResult] = []
        self._closed = False
        self._gradient_ready = False
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
        coarse = preview_step(self._full_triangles)
        stages = [("coarse", coarse), ("full", 1)] if self.coarse else [("full", 1)]
        for stage, step in self._stages(stages):
            normals = self.normals
            if stage == "coarse" and not self._gradient_ready and normals == "smooth":
                normals = "mesh"  # the smoothed gradient grid takes seconds the first time
            mesh = extract_surface(self.volume, iso, step=step, normals=normals,
                                   flip=self.flip, cancelled=lambda r=request: self._stale(r))
            if mesh is None:
                return
            if stage == "full":
                self._gradient_ready = True
                self._full_triangles = len(mesh.faces) or self._full_triangles
            with self._cv:
                if self._stale(request):
                    return
                self._results.append(MeshResult(request, iso, stage, mesh,
                                                time.perf_counter() - t0))


# -- the lattice in shared memory and the bake process ------------------------------------
class SharedLattice:
    """A `baking.Lattice` whose arrays live in shared memory blocks.

    The bake process attaches to the same blocks (`attach`) and writes texels; the viewer
    reads them for upload and saving.
    """

    def __init__(self, lattice, blocks: list, owner: bool) -> None:
        self.lattice, self.blocks, self.owner = lattice, blocks, owner

    @staticmethod
    def _layout(geometry, channels: int) -> dict[str, tuple[tuple, str]]:
        shape = tuple(geometry.shape)
        return {"values": ((*shape, channels), "float32"), "samples": (shape, "uint32"),
                "second": (shape, "float32"), "active": (shape, "bool"),
                "preview": ((*shape, channels), "float32"), "preview_paths": (shape, "uint16")}

    @classmethod
    def create(cls, geometry, channels: int, meta: dict, source=None) -> SharedLattice:
        """New shared arrays, zero or copied from the `source` lattice."""
        from multiprocessing import shared_memory

        from baking.lattice import Lattice

        arrays, blocks = {}, []
        for name, (shape, dtype) in cls._layout(geometry, channels).items():
            size = max(1, int(np.prod(shape)) * np.dtype(dtype).itemsize)
            block = shared_memory.SharedMemory(create=True, size=size)
            blocks.append(block)
            arr = np.ndarray(shape, dtype, buffer=block.buf)
            copied = None if source is None else getattr(source, name)
            arr[...] = 0 if copied is None else copied
            arrays[name] = arr
        lattice = Lattice(geometry, arrays["values"], arrays["samples"], arrays["second"],
                          arrays["active"], dict(meta), preview=arrays["preview"],
                          preview_paths=arrays["preview_paths"])
        return cls(lattice, blocks, owner=True)

    def describe(self) -> dict:
        """What `attach` needs (picklable)."""
        g = self.lattice.geometry
        return {"names": [b.name for b in self.blocks], "shape": list(g.shape),
                "lo": list(g.lo), "hi": list(g.hi), "channels": self.lattice.values.shape[-1],
                "meta": self.lattice.meta}

    @classmethod
    def attach(cls, description: dict) -> SharedLattice:
        """The same arrays, in another process."""
        from multiprocessing import shared_memory

        from baking.lattice import Lattice, LatticeGeometry

        geometry = LatticeGeometry(tuple(description["shape"]), tuple(description["lo"]),
                                   tuple(description["hi"]))
        layout = cls._layout(geometry, description["channels"])
        arrays, blocks = {}, []
        for (name, (shape, dtype)), block_name in zip(layout.items(), description["names"],
                                                      strict=True):
            # (a spawned child shares its parent's resource tracker: the block stays
            # registered once, and the owner's unlink unregisters it)
            block = shared_memory.SharedMemory(name=block_name)
            blocks.append(block)
            arrays[name] = np.ndarray(shape, dtype, buffer=block.buf)
        lattice = Lattice(geometry, arrays["values"], arrays["samples"], arrays["second"],
                          arrays["active"], dict(description["meta"]),
                          preview=arrays["preview"], preview_paths=arrays["preview_paths"])
        return cls(lattice, blocks, owner=False)

    def snapshot(self):
        """A private copy of the lattice (for saving while the bake goes on)."""
        from baking.lattice import Lattice

        lat = self.lattice
        samples = lat.samples.copy()
        values = np.where(samples[..., None] > 0, lat.values, 0).astype(np.float32)
        return Lattice(lat.geometry, values, samples, lat.second.copy(), lat.active.copy(),
                       json.loads(json.dumps(lat.meta)))

    def close(self) -> None:
        """Drop the arrays and release (and, as owner, unlink) the blocks."""
        self.lattice = None
        for block in self.blocks:
            try:
                block.close()
            except BufferError:  # a view is still alive somewhere; the OS frees it at exit
                pass
            if self.owner:
                try:
                    block.unlink()
                except FileNotFoundError:
                    pass
        self.blocks = []


def lattice_meta(volume: volumes.Volume, config) -> dict:
    """Metadata of a new lattice baked with `config` for `volume` (as `baking.bake` writes
    it)."""
    from baking.bake import path_settings
    from baking.lattice import volume_identity

    return {"kind": config.mode, "sh_order": config.sh_order if config.mode == "sh" else None,
            "scale": config.scale, "volume": volume_identity(volume),
            "config": config.to_dict(), "channels": path_settings(volume, config).channels}


def scene_budget() -> float:
    """Bytes the bake process may spend on cached level scenes: a quarter of the memory."""
    try:
        return 0.25 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2e9


def _bake_main(job: dict, inbox, outbox) -> None:
    """Entry point of the bake process: previews for the first view, the plan (while the
    previews go on and later views get theirs), then `baking.lazy.serve` until stopped."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the viewer's to handle
    try:
        os.nice(19)  # idle priority: the viewer (and llvmpipe's threads) come first
    except (AttributeError, OSError):
        pass
    process = None
    try:
        process = _BakeProcess(job, inbox, outbox)
        process.run()
    except Exception as exc:
        outbox.put(("error", f"{exc.__class__.__name__}: {exc}"))
    finally:
        if process is not None:
            process.shared.close()


class _BakeProcess:
    """The lazy bake's side of the link (runs in the spawned process)."""

    def __init__(self, job: dict, inbox, outbox) -> None:
        import multiprocessing

        from baking.config import BakeConfig
        from baking.preview import Previewer

        self.job, self.inbox, self.outbox = job, inbox, outbox
        self.shared = SharedLattice.attach(job["lattice"])
        self.volume = volumes.Volume(**job["volume"])
        self.config = BakeConfig.from_dict(job["config"])
        self.parent = multiprocessing.parent_process()
        self.workers = job["workers"] or os.cpu_count() or 1
        self.previewer = Previewer(self.volume, self.config, self.shared.lattice,
                                   self.workers)
        self.lit = None  # the last view given its first preview pass (held: not an id)
        self.waiting: list = []  # messages for `serve`, in order

    def receive(self, block: bool):
        """The next message (waiting for one if `block`); None when none is waiting and
        not `block`; "stop" when the viewer is gone."""
        while True:
            message = self.receive_within(0.5 if block else None)
            if message is not None or not block:
                return message

    def receive_within(self, timeout: float | None):
        """The next message within `timeout` seconds (None: only one already waiting), or
        None; "stop" when the viewer is gone."""
        import queue

        try:
            return self.inbox.get(block=timeout is not None, timeout=timeout)
        except queue.Empty:
            if self.parent is not None and not self.parent.is_alive():
                return "stop"
            return None

    def first_light(self, view) -> None:
        """The first preview pass of `view` (a few paths per visible texel, traced on its
        displayed surface); the others follow through `preview_step`."""
        if view is self.lit or view.visible is None or not len(view.visible):
            return
        self.lit = view
        self._announce(self.previewer.set_view(view.iso, view.visible))

    def preview_step(self) -> bool:
        """A slice of the queued preview passes; False when there was none."""
        if not self.previewer.busy:
            return False
        self._announce(self.previewer.step())
        return True

    def _announce(self, flat: np.ndarray) -> None:
        """Tell the viewer which texels changed, and which preview passes finished."""
        if len(flat):
            self.outbox.put(("texels", flat))
        while self.previewer.done:
            self.outbox.put(("preview", self.previewer.done.pop(0)))

    def _keep(self, message) -> bool:
        """Queue `message` for `serve`, lighting views at once; False on "stop"."""
        from baking.lazy import View

        if message == "stop":
            return False
        if isinstance(message, View):
            self.first_light(message)
        self.waiting.append(message)
        return True

    def _plan(self):
        """Make the Baker (its plan takes seconds to tens of seconds) on a thread while the
        preview passes go on and every new view gets its own; None when told to stop."""
        import threading

        from baking.bake import Baker
        from baking.lazy import scene_cache_size

        made: dict = {}

        def make() -> None:
            try:
                made["baker"] = Baker(self.volume, self.config, lattice=self.shared.lattice,
                                      workers=self.job["workers"], scene_cache=made["cache"])
            except BaseException as exc:  # re-raised below, in this thread
                made["error"] = exc

        made["cache"] = scene_cache_size(self.volume, self.job["iso"], self.config.max_levels,
                                         scene_budget())
        planner = threading.Thread(target=make, name="isolume-plan", daemon=True)
        planner.start()
        while planner.is_alive():
            message = self.receive_within(None if self.previewer.busy else 0.1)
            if message is not None and not self._keep(message):
                return None
            self.preview_step()
        if "error" in made:
            raise made["error"]
        return made["baker"], made["cache"]

    def run(self) -> None:
        from baking.lazy import LazyScheduler, View, serve
        from baking.preview import drop_inactive
        from baking.preview import warm_up as preview_warm_up

        preview_warm_up(self.volume)  # while the viewer opens its window
        self.outbox.put(("started", {"seconds": time.time() - self.job["started"]}))
        message = self.receive(True)  # the first view gets its first preview before the plan
        while not isinstance(message, View):
            if not self._keep(message):
                return
            message = self.receive(True)
        self._keep(message)
        t0 = time.perf_counter()
        active = self.shared.lattice.active  # the Baker replaces the lattice's attribute
        made = self._plan()
        if made is None:
            return
        baker, cache = made
        active[...] = baker.plan.active
        baker.lattice.active = active
        self.previewer.only_active = True
        stale = drop_inactive(self.shared.lattice)
        if len(stale):
            self.outbox.put(("texels", stale))
        self.outbox.put(("ready", {"seconds": time.perf_counter() - t0,
                                   "active": len(baker.plan.ids),
                                   "levels": len(baker.plan.levels),
                                   "scene_cache": cache, "meta": baker.lattice.meta}))
        scheduler = LazyScheduler(baker.plan, baker.geometry,
                                  self.shared.lattice.samples.reshape(-1),
                                  max_samples=self.config.samples,
                                  batch_paths=self.job["batch_paths"])

        def receive(block: bool):
            return self.waiting.pop(0) if self.waiting else self.receive(block)

        try:
            serve(baker, scheduler, receive, self.outbox.put, on_view=self.first_light,
                  before_batch=self.preview_step)
        finally:
            baker.close()


class BakeLink:
    """The viewer's side of the lazy bake process: send views, receive committed texels."""

    def __init__(self, volume: volumes.Volume, config, shared: SharedLattice,
                 workers: int | None, iso: float, batch_paths: int | None = None) -> None:
        import multiprocessing

        from baking.lazy import BATCH_PATHS

        ctx = multiprocessing.get_context("spawn")
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        job = {
            "lattice": shared.describe(),
            "volume": {"data": volume.data, "spacing": volume.spacing, "origin": volume.origin,
                       "name": volume.name, "source": volume.source,
                       "suggested_iso": volume.suggested_iso},
            "config": config.to_dict(), "workers": workers, "iso": float(iso),
            "batch_paths": batch_paths or BATCH_PATHS, "started": time.time(),
        }
        self.started = time.perf_counter()
        self.process = ctx.Process(target=_bake_main, args=(job, self.inbox, self.outbox),
                                   name="isolume-bake", daemon=True)
        self.process.start()
        self.ready: dict | None = None
        self.progress = None
        self.stats: dict = {}
        self.error: str | None = None
        self.paused = False
        self.paused_ack = False
        self.history: list[tuple[float, object]] = []
        self.previews: list[tuple[float, dict]] = []  # (seconds since start, figures) per pass
        self.warm: dict | None = None  # the process is ready for views (its start-up time)

    def send_view(self, view) -> None:
        self.inbox.put(view)

    def pause(self, paused: bool) -> None:
        self.paused = bool(paused)
        self.inbox.put("pause" if paused else "resume")

    def poll(self) -> list[np.ndarray]:
        """Handle the messages that arrived; return the flat ids of committed texels."""
        import queue

        texels = []
        while True:
            try:
                message = self.outbox.get_nowait()
            except queue.Empty:
                break
            kind = message[0]
            if kind == "texels":
                texels.append(message[1])
            elif kind == "progress":
                self.progress, self.stats = message[1], message[2]
                self.history.append((time.perf_counter() - self.started, message[1]))
            elif kind == "ready":
                self.ready = message[1]
            elif kind == "paused":
                self.paused_ack = message[1]
            elif kind == "started":
                self.warm = message[1]
            elif kind == "preview":
                self.previews.append((time.perf_counter() - self.started, message[1]))
            elif kind == "error":
                self.error = message[1]
        if self.error is None and self.ready is None and not self.process.is_alive():
            self.error = f"the bake process ended (exit code {self.process.exitcode})"
        return texels

    def stop(self, timeout: float = 15.0) -> None:
        """Ask the process to finish its batch and exit; terminate it if it does not (at
        once while it is still planning: it has written nothing yet)."""
        self.poll()
        if self.process.is_alive() and self.ready is not None:
            self.inbox.put("stop")
            self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2)
        for q in (self.inbox, self.outbox):
            q.cancel_join_thread()
            q.close()


# -- re-uploading texels ------------------------------------------------------------------
def upload_box(textures, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> None:
    """Re-upload texels lo ≤ (z, y, x) < hi of `textures.lattice` into its GL textures
    (irradiance premultiplied by validity, and validity), as `LatticeTextures` stores them."""
    lat = textures.lattice
    (z0, y0, x0), (z1, y1, x1) = lo, hi
    region = np.s_[z0:z1, y0:y1, x0:x1]
    premultiplied = np.ascontiguousarray(lat.displayed(region)[..., :3])  # 0 where not shown
    valid = np.where(lat.shown(region), 255, 0).astype(np.uint8)
    viewport = (x0, y0, z0, x1 - x0, y1 - y0, z1 - z0)
    textures.irradiance.write(premultiplied.tobytes(), viewport=viewport, alignment=4)
    textures.valid.write(valid.tobytes(), viewport=viewport, alignment=1)


class TexelUploader:
    """Tracks which BRICK³ blocks hold newly committed texels and re-uploads them.

    Irradiance lattices are re-uploaded block by block (`upload_box`); SH lattices, whose
    packing `LatticeTextures` does per z-slab, by the z-slabs of the dirty blocks."""

    def __init__(self, textures) -> None:
        self.textures = textures
        self.shape = tuple(textures.lattice.geometry.shape)
        self.dirty = np.zeros([-(-n // BRICK) for n in self.shape], bool)
        self.uploaded = 0

    def mark(self, flat_ids: np.ndarray) -> None:
        """Note (N,) flat texel ids whose values changed."""
        if len(flat_ids) == 0:
            return
        k, j, i = np.unravel_index(np.asarray(flat_ids, np.int64), self.shape)
        self.dirty[k // BRICK, j // BRICK, i // BRICK] = True

    @property
    def pending(self) -> int:
        """Blocks waiting for upload."""
        return int(self.dirty.sum())

    def upload(self, budget_s: float | None = UPLOAD_BUDGET_S) -> int:
        """Upload dirty blocks until `budget_s` seconds are spent (None: all); returns how
        many were uploaded."""
        t0, n = time.perf_counter(), 0
        if self.textures.kind != "irradiance":
            for k in np.flatnonzero(self.dirty.any(axis=(1, 2))):
                self.textures.update(int(k) * BRICK, min((int(k) + 1) * BRICK, self.shape[0]))
                n += int(self.dirty[k].sum())
                self.dirty[k] = False
                if budget_s is not None and time.perf_counter() - t0 > budget_s:
                    break
            self.uploaded += n
            return n
        for b in np.argwhere(self.dirty):
            lo = tuple(int(v) * BRICK for v in b)
            hi = tuple(min(v + BRICK, s) for v, s in zip(lo, self.shape, strict=True))
            upload_box(self.textures, lo, hi)
            self.dirty[tuple(b)] = False
            n += 1
            if budget_s is not None and time.perf_counter() - t0 > budget_s:
                break
        self.uploaded += n
        return n


def check_textures(textures) -> dict:
    """Read the GL textures back and compare them with the lattice.

    Returns:
        {"texels": texels shown (computed or previewed), "computed": texels
        with samples, "max_rel_error":
        largest |GL − lattice| / max(RGB) over those texels (RGB9_E5 keeps 9 mantissa
        bits: ≤ 2⁻⁹ when rounding),
        "valid_mismatch": texels whose validity differs, "uncomputed_nonzero": texels not
        shown with a non-zero value}; SH lattices: the validity only.
    """
    lat = textures.lattice
    z, y, x = lat.geometry.shape
    gl_valid = np.frombuffer(textures.valid.read(), np.uint8).reshape(z, y, x)
    computed = lat.shown()
    if textures.kind != "irradiance":  # SH packing is LatticeTextures' own: validity only
        return {"texels": int(computed.sum()), "computed": int((lat.samples > 0).sum()),
                "max_rel_error": None,
                "valid_mismatch": int(((gl_valid > 127) != computed).sum()),
                "uncomputed_nonzero": None}
    gl_rgb = np.frombuffer(textures.irradiance.read(), np.float32).reshape(z, y, x, 3)
    want = lat.displayed()[..., :3][computed].astype(np.float64)
    got = gl_rgb[computed].astype(np.float64)
    scale = np.maximum(want.max(axis=1, keepdims=True), 1e-30)
    rel = np.abs(got - want) / scale
    return {"texels": int(computed.sum()), "computed": int((lat.samples > 0).sum()),
            "max_rel_error": float(rel.max()) if len(rel) else 0.0,
            "valid_mismatch": int(((gl_valid > 127) != computed).sum()),
            "uncomputed_nonzero": int((gl_rgb[~computed] != 0).any(axis=-1).sum())}


# -- the viewer ---------------------------------------------------------------------------
@dataclass
class ViewState:
    """What the user controls (besides the camera)."""

    iso: float
    shading: str
    exposure: float
    light: tuple[float, float] | None = None  # None: key light fixed to the camera
    show_ui: bool = True


@dataclass
class Extraction:
    """Figures of one isovalue change: seconds to the coarse and full surface, frames drawn
    meanwhile and the longest gap between frames."""

    iso: float
    requested: float
    coarse_s: float | None = None
    full_s: float | None = None
    frames: int = 0
    max_gap_ms: float = 0.0
    triangles: int = 0


@dataclass
class FrameClock:
    """Frame times of the render thread."""

    times: deque = field(default_factory=lambda: deque(maxlen=120))
    all_ms: list = field(default_factory=list)
    interactive_ms: list = field(default_factory=list)
    last_end: float | None = None
    count: int = 0

    def add(self, start: float, end: float) -> None:
        self.times.append(end - start)
        self.all_ms.append(1000 * (end - start))
        self.last_end = end
        self.count += 1

    @property
    def mean_ms(self) -> float:
        return 1000 * float(np.mean(self.times)) if self.times else 0.0


@dataclass
class Quality:
    """Detail while the user moves the camera or light: the preview mesh first, then lower
    resolutions, until a frame takes about INTERACTIVE_MS (software GL needs both; a GPU
    needs neither). Kept between interactions; full detail returns when the motion stops."""

    level: int = 0
    coarse: bool = False

    @property
    def scale(self) -> float:
        return RENDER_SCALES[self.level]

    def adapt(self, frame_ms: float, full_triangles: int) -> None:
        """Adjust after an interactive frame that took `frame_ms`."""
        if frame_ms > 1.3 * INTERACTIVE_MS:
            if not self.coarse and full_triangles > PREVIEW_TRIANGLES:
                self.coarse = True
            elif self.level < len(RENDER_SCALES) - 1:
                self.level += 1
        elif frame_ms < 0.6 * INTERACTIVE_MS and self.level > 0:
            self.level -= 1


_GL_READ_FRAMEBUFFER, _GL_DRAW_FRAMEBUFFER = 0x8CA8, 0x8CA9
_GL_COLOR_BUFFER_BIT, _GL_LINEAR = 0x4000, 0x2601


class Blitter:
    """Scales an 8-bit render target onto the window (glBlitFramebuffer, linear filter),
    which moderngl's ``copy_framebuffer`` cannot do (it copies 1:1)."""

    def __init__(self, ctx) -> None:
        import ctypes

        proc = ctx.extra["proc_address"]
        self.ctx = ctx
        self._bind = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_uint)(
            proc("glBindFramebuffer"))
        self._blit = ctypes.CFUNCTYPE(None, *([ctypes.c_int] * 8), ctypes.c_uint,
                                      ctypes.c_uint)(proc("glBlitFramebuffer"))

    def to_screen(self, fbo, src: tuple[int, int], dst: tuple[int, int]) -> None:
        self._bind(_GL_READ_FRAMEBUFFER, fbo.glo)
        self._bind(_GL_DRAW_FRAMEBUFFER, 0)
        self._blit(0, 0, src[0], src[1], 0, 0, dst[0], dst[1], _GL_COLOR_BUFFER_BIT, _GL_LINEAR)
        self.ctx.screen.viewport = (0, 0, dst[0], dst[1])
        self.ctx.screen.use()  # rebinds 0 for both, as moderngl believes


class ViewerError(ValueError):
    """A request the viewer cannot honour (bad script step, missing lattice); one line."""


class Viewer:
    """The interactive viewer: window, renderer, UI, workers and script."""

    def __init__(self, volume: volumes.Volume, iso: float, lattice, options: Options) -> None:
        from .glcontext import create_window
        from .render import SHADING_MODES, RenderSettings, SurfaceRenderer, default_camera

        self.volume, self.options = volume, options
        self.window = create_window(options.size, f"isolume — {volume.name}")
        self.ctx = self.window.ctx
        self.renderer = SurfaceRenderer(self.ctx)
        self.render_fields = {f.name for f in fields(RenderSettings)}
        self.modes = tuple(SHADING_MODES)
        self.home = default_camera(volume)
        self.camera = self.home
        self.ui = self._make_ui() if options.ui else None
        self.message = ""
        self.shared: SharedLattice | None = None
        self.bake: BakeLink | None = None
        self.uploader: TexelUploader | None = None
        self.static_lattice = lattice
        self.albedo = (0.8, 0.8, 0.8)
        self._usable: tuple[str, ...] | None = None
        self.renderer.set_bounds(*volume.box)  # shadows and fog do not follow the isovalue
        self._setup_lattice(lattice, iso)
        shading = options.shading or (self.renderer.lattice.kind if self.renderer.lattice
                                      else "phong_hemi")
        self.state = ViewState(iso, shading, options.exposure)
        self._check_mode(shading)
        self._ensure_texel_isovalues(shading)
        self.mesh_worker = MeshWorker(volume, normals=options.normals,
                                      flip=options.flip_normals)
        self.mesh_stage: str | None = None
        self.mesh_iso: float | None = None
        self.meshes: dict[str, volumes.Mesh] = {}
        self.on_gpu: str | None = None
        self.quality = Quality()
        self.blitter = Blitter(self.ctx)
        self.last_motion = 0.0
        self.reduced = False
        self.mesh_info = "extracting..."
        self.extractions: list[Extraction] = []
        self.clock = FrameClock()
        self.dirty = True
        self.last_input = 0.0
        self.view_sent: tuple | None = None
        self.view_seen: tuple | None = None
        self.view_since = 0.0
        self.drag = None
        self.pending_press: str | None = None
        self.quit = False
        self.checks: list[dict] = []
        from .viewer_script import ScriptRunner

        self.script = ScriptRunner(self._script_commands(options))
        self._install_callbacks()
        self.request_iso(iso)

    # -- setup ---------------------------------------------------------------------------
    def _make_ui(self):
        from .ui import ImGuiLayer

        try:
            return ImGuiLayer(self.window.glfw, self.window.ui_scale)
        except ImportError:
            print("isolume: note: imgui-bundle is not installed; no control panel "
                  "(pip install imgui-bundle)", file=sys.stderr)
        except RuntimeError as exc:
            print(f"isolume: note: {exc}; no control panel", file=sys.stderr)
        return None

    def _setup_lattice(self, lattice, iso: float) -> None:
        """Show `lattice` (if any) and start the lazy bake when it is missing or incomplete."""
        from baking.config import BakeConfig

        config = None
        if lattice is not None:
            config = BakeConfig.from_dict(lattice.meta["config"])
            self.albedo = tuple(config.albedo)
            done = lattice.samples[lattice.active] >= config.samples
            if done.all() or not self.options.bake:
                self._show_lattice(lattice)
                return
        if not self.options.bake:
            return
        if config is None:
            config = BakeConfig(mode=self.options.bake_mode, env=self.options.bake_env,
                                samples=self.options.bake_samples,
                                max_levels=self.options.bake_max_levels)
        from baking.lattice import LatticeGeometry

        geometry = LatticeGeometry.for_volume(self.volume, config.scale)
        meta = lattice.meta if lattice is not None else lattice_meta(self.volume, config)
        self.shared = SharedLattice.create(geometry, meta["channels"], meta, lattice)
        self.static_lattice = None
        if self._show_lattice(self.shared.lattice):
            self.uploader = TexelUploader(self.renderer.lattice)
        self.bake = BakeLink(self.volume, config, self.shared, self.options.bake_workers, iso)

    def _show_lattice(self, lattice) -> bool:
        """Upload `lattice` (and, for SH, the environment it was baked for)."""
        try:
            self.renderer.set_lattice(lattice)
            if lattice.kind == "sh":
                from .cli import _environment_coefficients

                self.renderer.set_environment(_environment_coefficients(None, lattice, "none"))
        except ValueError as exc:
            self.message = f"lattice not shown: {exc}"
            self.renderer.set_lattice(None)
            return False
        return True

    def usable_modes(self) -> tuple[str, ...]:
        """Shading modes that can be drawn now (`SurfaceRenderer.check_mode`); the
        closest-isovalue lookup counts as usable with an irradiance lattice, its texel
        isovalues are computed when it is first chosen."""
        if self._usable is None:
            from .render import SHADING_MODES

            lattice = self.renderer.lattice
            out = []
            for name in self.modes:
                try:
                    self.renderer.check_mode(name)
                except ValueError:
                    closest = getattr(SHADING_MODES[name], "lookup", "") == "closest"
                    if not (closest and lattice is not None and lattice.kind == "irradiance"):
                        continue
                out.append(name)
            self._usable = tuple(out)
        return self._usable

    def _ensure_texel_isovalues(self, mode: str) -> None:
        """Upload the texel isovalues the closest-isovalue lookup needs (once)."""
        from baking.plan import texel_values

        from .render import SHADING_MODES

        textures = self.renderer.lattice
        closest = getattr(SHADING_MODES[mode], "lookup", "") == "closest"
        if not closest or textures is None or textures.texel_iso is not None:
            return
        lattice = textures.lattice
        self.renderer.set_lattice(lattice, texel_values(self.volume, lattice.geometry))
        if self.uploader is not None:  # fresh textures hold every texel computed so far
            self.uploader = TexelUploader(self.renderer.lattice)
        self._usable = None

    def _script_commands(self, options: Options) -> list:
        from .viewer_script import Command

        commands = list(options.script)
        if options.frames is not None:
            if not commands:
                commands.append(Command("wait-mesh", (), 0))
            commands += [Command("frames", (options.frames,), 0), Command("quit", (), 0)]
        return commands

    def _install_callbacks(self) -> None:
        glfw, handle = self.window.glfw, self.window.handle
        glfw.set_cursor_pos_callback(handle, self._on_cursor)
        glfw.set_mouse_button_callback(handle, self._on_mouse_button)
        glfw.set_scroll_callback(handle, self._on_scroll)
        glfw.set_key_callback(handle, self._on_key)
        glfw.set_char_callback(handle, self._on_char)
        glfw.set_window_focus_callback(handle, self._on_focus)
        glfw.set_framebuffer_size_callback(handle, lambda *_: self._touch())
        glfw.set_window_refresh_callback(handle, lambda *_: self._touch())

    def _touch(self) -> None:
        """Something on screen changed: draw again."""
        self.dirty = True

    def _moved(self) -> None:
        """The user moves the camera or light (interactive quality applies)."""
        self.last_motion = time.perf_counter()
        self._touch()

    @property
    def _ui_shown(self) -> bool:
        return self.ui is not None and self.state.show_ui

    def _interacting(self, now: float) -> bool:
        return self.drag is not None or now - self.last_motion < 0.3

    # -- input: UI first, then the camera ------------------------------------------------
    def _input(self) -> None:
        self.last_input = time.perf_counter()
        self.dirty = True

    def _on_cursor(self, _handle, x: float, y: float) -> None:
        self._input()
        if self.ui is not None:
            self.ui.mouse_pos(x, y)
        if self.drag is None:
            return
        dx, dy = x - self.drag.x, y - self.drag.y
        self.drag.x, self.drag.y = x, y
        self._drag_by(self.drag.target, dx, dy)

    def _drag_by(self, target: str, dx: float, dy: float) -> None:
        from .ui import ROTATE_DEG_PER_PX, orbit, pan, pan_per_pixel

        if target == "rotate":
            self.camera = orbit(self.camera, -dx * ROTATE_DEG_PER_PX, dy * ROTATE_DEG_PER_PX)
        elif target == "pan":
            k = pan_per_pixel(self.camera, self.window.window_size[1])
            self.camera = pan(self.camera, -dx * k, dy * k)
        elif target == "light":
            az, el = self._light_angles()
            self.set_light((az + dx * ROTATE_DEG_PER_PX,
                            float(np.clip(el - dy * ROTATE_DEG_PER_PX, -90, 90))))
        self._moved()

    def _on_mouse_button(self, _handle, button: int, action: int, mods: int) -> None:
        from .ui import drag_target

        glfw = self.window.glfw
        self._input()
        if self.ui is not None:
            self.ui.mouse_button(button, action == glfw.PRESS)
        if action == glfw.RELEASE:
            self.drag = self.pending_press = None
            return
        target = drag_target(button, bool(mods & glfw.MOD_SHIFT), bool(mods & glfw.MOD_CONTROL))
        if target is None:
            return
        if self._ui_shown:
            # ImGui decides at its next frame whether the press is its own (it only then
            # knows what lies under the pointer); `_confirm_press` starts the drag if not
            self.pending_press = target
        else:
            self._start_drag(target)

    def _start_drag(self, target: str) -> None:
        from .ui import Drag

        x, y = self.window.glfw.get_cursor_pos(self.window.handle)
        self.drag = Drag(target, x, y)

    def _confirm_press(self) -> None:
        """After the UI's new frame: a pending press drags the camera unless ImGui took it."""
        if self.pending_press is not None and not self.ui.wants_mouse:
            self._start_drag(self.pending_press)
        self.pending_press = None

    def _on_scroll(self, _handle, dx: float, dy: float) -> None:
        from .ui import ZOOM_PER_WHEEL, zoom

        self._input()
        if self.ui is not None:
            self.ui.scroll(dx, dy)
            if self._ui_shown and self.ui.wants_mouse:
                return
        self.camera = zoom(self.camera, ZOOM_PER_WHEEL ** -dy)
        self._moved()

    def _on_char(self, _handle, codepoint: int) -> None:
        self._input()
        if self.ui is not None:
            self.ui.char(codepoint)

    def _on_focus(self, _handle, focused: int) -> None:
        self._input()
        if self.ui is not None:
            self.ui.focus(bool(focused))

    def _on_key(self, _handle, key: int, _scancode: int, action: int, mods: int) -> None:
        glfw = self.window.glfw
        self._input()
        if self.ui is not None:
            self.ui.key(key, action != glfw.RELEASE, mods)
            if self._ui_shown and self.ui.wants_keyboard:
                return
        if action == glfw.RELEASE:
            return
        from .ui import key_action

        requested = key_action(glfw, key, mods, self.modes)
        if requested is not None:
            self.apply(requested)

    # -- actions (keys, panel and script all end here) -----------------------------------
    def request_iso(self, iso: float) -> None:
        """Show the isosurface at `iso` (clamped inside the data range)."""
        lo, hi = self.volume.value_range
        eps = 1e-6 * (hi - lo)
        iso = float(np.clip(iso, lo + eps, hi - eps))
        self.state.iso = iso
        self.mesh_worker.request(iso)
        self.extractions.append(Extraction(iso, time.perf_counter()))
        self._touch()

    def step_iso(self, steps: int) -> None:
        lo, hi = self.volume.value_range
        self.request_iso(self.state.iso + steps * (hi - lo) / ISO_STEPS)

    def _check_mode(self, mode: str) -> None:
        if mode not in self.modes:
            raise ViewerError(f"unknown shading mode {mode!r}; expected one of "
                              f"{', '.join(self.modes)}")
        if mode in self.usable_modes():
            return
        if self.renderer.lattice is None:
            raise ViewerError(f"shading {mode!r} needs a lattice: pass --lattice FILE, or "
                              "leave out --no-bake to bake one lazily")
        raise ViewerError(f"shading {mode!r} cannot be drawn from the {self.renderer.lattice.kind}"
                          " lattice shown (irradiance modes need an irradiance lattice, sh an "
                          "SH one: --bake-mode)")

    def set_mode(self, mode: str) -> None:
        self._check_mode(mode)
        self._ensure_texel_isovalues(mode)
        self.state.shading = mode
        self._touch()

    def set_exposure(self, exposure: float) -> None:
        self.state.exposure = float(np.clip(exposure, 1e-3, 1e3))
        self._touch()

    def set_light(self, angles: tuple[float, float] | None) -> None:
        """World-fixed light at (azimuth, elevation) degrees, or None: fixed to the camera."""
        self.state.light = None if angles is None else (float(angles[0]) % 360.0,
                                                        float(angles[1]))
        self._touch()

    def _light_angles(self) -> tuple[float, float]:
        """Current light direction as angles (from the camera-fixed light if need be)."""
        from .render import key_direction
        from .ui import angles_from_direction

        if self.state.light is not None:
            return self.state.light
        if self.state.shading == "sh":  # the environment starts as loaded
            return (0.0, 0.0)
        return angles_from_direction(key_direction(self.camera, self._settings((1, 1))))

    def apply(self, action) -> None:
        """Apply an `app.ui.Action` (from the panel or a key); problems become the status
        message."""
        name, value = action.name, action.value
        simple = {
            "iso": lambda: self.request_iso(value),
            "iso_step": lambda: self.step_iso(value),
            "mode": lambda: self.set_mode(value),
            "exposure": lambda: self.set_exposure(value),
            "exposure_by": lambda: self.set_exposure(self.state.exposure * value),
            "light": lambda: self.set_light(value),
            "light_camera": lambda: self.set_light(None if value else self._light_angles()),
            "toggle_light": lambda: self.set_light(
                None if self.state.light is not None else self._light_angles()),
            "reset_camera": lambda: setattr(self, "camera", self.home),
            "screenshot": self.screenshot,
            "save_lattice": self.save_lattice,
            "pause_bake": lambda: self.bake and self.bake.pause(value),
            "toggle_bake": lambda: self.bake and self.bake.pause(not self.bake.paused),
            "toggle_ui": lambda: setattr(self.state, "show_ui", not self.state.show_ui),
            "quit": lambda: setattr(self, "quit", True),
        }
        try:
            simple[name]()
        except (ViewerError, OSError) as exc:
            self.message = str(exc)
        self._touch()

    def screenshot(self, path: str | os.PathLike | None = None) -> tuple[Path, Path]:
        """Write the current view (without the panel) as PNG (sRGB) and EXR (linear
        radiance, before exposure) next to each other; returns both paths."""
        from .images import write_exr, write_png
        from .viewer_script import screenshot_paths

        if path is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            path = Path(f"isolume-{self.volume.name}-{stamp}.png")
        png, exr = screenshot_paths(path)
        if not png.parent.is_dir():
            raise ViewerError(f"screenshot {png}: directory {png.parent} does not exist")
        frame = self.renderer.render(self.camera, self._settings(self._frame_size()))
        write_png(png, frame.srgb)
        write_exr(exr, frame.linear)
        self.message = f"wrote {png} and {exr}"
        print(f"isolume: {self.message}")
        return png, exr

    def save_lattice(self, path: str | os.PathLike | None = None) -> Path | None:
        """Write the lattice being shown/baked to `path` (default: --lattice, else
        isolume-NAME.npz)."""
        lattice = self.shared.snapshot() if self.shared is not None else None
        if lattice is None:
            self.message = "no lazily baked lattice to save"
            return None
        if self.bake is not None and self.bake.ready is not None:
            lattice.meta.update(self.bake.ready["meta"])
        path = Path(path or self.options.lattice_path or f"isolume-{self.volume.name}.npz")
        lattice.save(path)
        done = int((lattice.samples > 0).sum())
        self.message = f"saved {path} ({done:,} texels computed)"
        print(f"isolume: {self.message}")
        return path

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> int:
        """Run until the window closes, `quit`, or the script/--frames ends it."""
        glfw = self.window.glfw
        while not (self.quit or self.window.should_close()):
            if self._wants_frame():
                glfw.poll_events()
            else:
                glfw.wait_events_timeout(0.03)
            self._receive_mesh()
            self._receive_bake()
            self.script.step(self)
            self._update_view()
            if self._wants_frame():
                self.draw_frame()
                self._pace()
        return 0

    def _pace(self) -> None:
        """While a surface is extracted, leave the worker at least a third of the time
        (drawing holds the GIL; waiting for events does not)."""
        if self._extraction_pending() and self.clock.times:
            self.window.glfw.wait_events_timeout(min(0.5 * self.clock.times[-1], 0.05))

    def _wants_frame(self) -> bool:
        now = time.perf_counter()
        recent_input = now - self.last_input < 0.25
        settle = self.reduced and not self._interacting(now)  # one full-detail frame
        return self.dirty or recent_input or settle or self.script.forces_frames

    def _frame_size(self) -> tuple[int, int]:
        w, h = self.window.framebuffer_size
        return max(w, 1), max(h, 1)

    def _settings(self, size: tuple[int, int]):
        from .render import RenderSettings
        from .ui import direction_from_angles

        kw = {"size": size, "shading": self.state.shading, "exposure": self.state.exposure,
              "albedo": self.albedo}
        if self.state.light is not None:
            kw["key_dir"] = tuple(direction_from_angles(*self.state.light))
        if "env_rotation" in self.render_fields:
            kw["env_rotation"] = self.state.light or (0.0, 0.0)
        return RenderSettings(**kw)

    def draw_frame(self) -> None:
        """Draw the scene and the panel, swap, and account the frame."""
        start = time.perf_counter()
        w, h = self.window.framebuffer_size
        if w == 0 or h == 0:  # minimised
            self.dirty = False
            return
        if self._ui_shown:
            self.ui.new_frame(self.window.window_size, (w, h), start)
            self._confirm_press()
            from .ui import draw_panel

            for action in draw_panel(self.ui.imgui, self._panel_model()):
                self.apply(action)
        interacting = self._interacting(start)
        self._sync_mesh(preview=(interacting and self.quality.coarse) or self._heavy_wait())
        scale = self.quality.scale if interacting else 1.0
        try:
            self._draw_scene((w, h), scale)
        except ValueError as exc:  # app.render.RenderError: a mode without what it needs
            self.message = f"shading {self.state.shading!r}: {exc}; back to phong_hemi"
            self.state.shading = "phong_hemi"
            self._draw_scene((w, h), scale)
        if self._ui_shown:
            self.ui.render()
        self.script.before_swap(self)
        self.window.swap()
        end = time.perf_counter()
        self._account_frame(start, end)
        if interacting:
            full = self.meshes.get("full")
            self.quality.adapt(1000 * (end - start), len(full.faces) if full else 0)
            self.clock.interactive_ms.append(1000 * (end - start))
        # drawn with less detail than there is: one more frame once the motion stops
        self.reduced = (interacting and scale < 1) or (self.on_gpu == "coarse"
                                                       and "full" in self.meshes)
        self.dirty = False

    def _extraction_pending(self) -> bool:
        return bool(self.extractions) and self.extractions[-1].full_s is None

    def _heavy_wait(self) -> bool:
        """A new surface is being extracted and the full one on screen is big: show the
        preview meanwhile (software GL holds the GIL while it draws, which would starve
        the extraction)."""
        full = self.meshes.get("full")
        return (self._extraction_pending() and full is not None
                and len(full.faces) > PREVIEW_TRIANGLES)

    def _draw_scene(self, size: tuple[int, int], scale: float) -> None:
        """Render at `scale` × the framebuffer `size` and put it on the window."""
        w, h = size
        small = (max(1, round(w * scale)), max(1, round(h * scale)))
        settings = self._settings(small)
        targets = self.renderer.draw_hdr(self.camera, settings)
        if small == size:
            self.ctx.screen.viewport = (0, 0, w, h)
            self.renderer.resolve(targets, settings, fbo=self.ctx.screen)
        else:
            self.renderer.resolve(targets, settings)
            self.blitter.to_screen(targets.ldr, small, size)

    def _sync_mesh(self, preview: bool) -> None:
        """Put the preview or the full surface of the current isovalue on the GPU."""
        want = "coarse" if preview and "coarse" in self.meshes else "full"
        if want not in self.meshes:
            want = "coarse"
        if want == self.on_gpu or want not in self.meshes:
            return
        mesh = self.meshes[want]
        self.renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        self.on_gpu = want

    def _account_frame(self, start: float, end: float) -> None:
        previous = self.clock.last_end
        self.clock.add(start, end)
        pending = self.extractions[-1] if self.extractions else None
        if pending is not None and pending.full_s is None:
            pending.frames += 1
            if previous is not None and previous >= pending.requested:
                pending.max_gap_ms = max(pending.max_gap_ms, 1000 * (end - previous))
        self.script.frame_done()

    def _receive_mesh(self) -> None:
        if self.mesh_worker.error:
            self.message, self.mesh_worker.error = self.mesh_worker.error, None
        for result in self.mesh_worker.poll():
            mesh = result.mesh
            if result.stage == "lod":  # a lighter preview for moving the camera
                if result.iso == self.mesh_iso:
                    self.meshes["coarse"] = mesh
                continue
            if result.iso != self.mesh_iso:
                self.meshes = {}
            self.meshes[result.stage] = mesh
            self.on_gpu = None
            self._sync_mesh(preview=self.quality.coarse
                            and self._interacting(time.perf_counter()))
            self.mesh_stage, self.mesh_iso = result.stage, result.iso
            stage = "full resolution" if result.stage == "full" else "preview"
            self.mesh_info = (mesh.message if mesh.empty else
                              f"{stage}: {len(mesh.faces):,} triangles, "
                              f"{len(mesh.vertices):,} vertices")
            record = self.extractions[-1]
            if result.stage == "coarse":
                record.coarse_s = result.seconds
            else:
                record.full_s, record.triangles = result.seconds, len(mesh.faces)
            self._touch()

    def _receive_bake(self) -> None:
        if self.bake is None:
            return
        for ids in self.bake.poll():
            if self.uploader is not None:
                self.uploader.mark(ids)
        if self.bake.error:
            self.message = f"lazy bake stopped: {self.bake.error}"
        if self.uploader is not None and self.uploader.pending:
            self.uploader.upload()
            if self.state.shading in self._lattice_modes():
                self._touch()

    def _lattice_modes(self) -> tuple[str, ...]:
        from .render import LATTICE_MODES

        return tuple(LATTICE_MODES)

    def _update_view(self) -> None:
        """Tell the bake process what is on screen once the view has settled."""
        if self.bake is None or self.mesh_iso != self.state.iso or self.mesh_stage is None:
            return
        key = (self.state.iso, self.camera, self.mesh_stage == "full")
        now = time.perf_counter()
        if key != self.view_seen:  # the view changed: wait until it holds still
            self.view_seen, self.view_since = key, now
            return
        if key == self.view_sent or now - self.view_since < SETTLE_S or self.drag is not None:
            return
        from baking.lazy import View, visible_cells

        cells = visible_cells(self.shared.lattice.geometry, self._visible_points())
        self.bake.send_view(View(self.state.iso, tuple(float(v) for v in self.camera.eye),
                                 cells))
        self.view_sent = key

    def _visible_points(self) -> np.ndarray:
        """(N, 3) world positions of the surface under (every other) pixel."""
        w, h = self._frame_size()
        scale = min(1.0, 512.0 / max(w, h))  # a position pass of at most 512 pixels across
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        settings = replace(self._settings(size), shading="position")
        frame = self.renderer.render(self.camera, settings)
        return frame.linear[frame.mask]

    # -- panel ---------------------------------------------------------------------------
    def _panel_model(self):
        from .ui import PanelModel

        z, y, x = self.volume.data.shape
        enabled = self.usable_modes()
        light_note = ""
        if self.state.shading == "sh":
            light_note = "The light controls rotate the environment (SH transfer)."
        elif self.state.shading in self._lattice_modes():
            light_note = ("The light is baked into the lattice (fixed); rotating it moves "
                          "only the fallback light of texels not computed yet.")
        fractions, lines = self._bake_status()
        return PanelModel(
            title=f"{self.volume.name}  {x}x{y}x{z}", iso=self.state.iso,
            iso_range=self.volume.value_range, mesh_status=self.mesh_info, modes=self.modes,
            enabled=enabled, mode=self.state.shading, exposure=self.state.exposure,
            light=self.state.light, light_note=light_note, bake_lines=lines,
            bake_fractions=fractions, bake_paused=bool(self.bake and self.bake.paused),
            can_bake=self.bake is not None, can_save=self.shared is not None,
            frame_ms=self.clock.mean_ms, size=self._frame_size(), message=self.message,
        )

    def _bake_status(self) -> tuple[tuple[float, float] | None, tuple[str, ...]]:
        if self.bake is None:
            if self.static_lattice is not None:
                return None, ("lattice loaded (complete)",)
            return None, ()
        if self.bake.error:
            return None, (f"error: {self.bake.error}",)
        preview = self._preview_line()
        if self.bake.ready is None:
            return None, (f"planning the bake... {time.perf_counter() - self.bake.started:.0f} s",
                          preview)
        p, s = self.bake.progress, self.bake.stats
        if p is None:
            return None, ("waiting for the surface", preview)
        stage = "done for this view" if p.stage is None else f"{p.stage[0]} to {p.stage[1]} paths"
        if p.surface == 0:
            stage = "this isovalue lies outside the baked range"
        rate = s.get("paths", 0) / max(s.get("seconds", 0.0), 1e-9)
        lines = (preview, f"{stage}, {rate:,.0f} paths/s",
                 f"{p.visible:,} visible / {p.surface:,} surface texels")
        return (p.visible_fraction, p.surface_fraction), lines

    def _preview_line(self) -> str:
        """The last preview pass done for the isovalue on screen ("" when none)."""
        done = [f for _, f in self.bake.previews if f["iso"] == self.state.iso]
        return f"preview: {done[-1]['paths']} paths/texel on this surface" if done else ""

    # -- figures and shutdown ------------------------------------------------------------
    def figures(self) -> dict:
        """What `--stats` writes."""
        times = np.array(self.clock.all_ms) if self.clock.all_ms else np.zeros(1)
        bake = None
        if self.bake is not None:
            p = self.bake.progress
            bake = {"ready": {k: v for k, v in (self.bake.ready or {}).items() if k != "meta"},
                    "progress": asdict(p) if p is not None else None,
                    "previews": [{"at_s": at, **f} for at, f in self.bake.previews],
                    "stats": self.bake.stats, "error": self.bake.error,
                    "blocks_uploaded": self.uploader.uploaded if self.uploader else 0}
        cam = self.camera
        state = asdict(self.state) | {"camera": {
            "azimuth": cam.azimuth, "elevation": cam.elevation, "distance": cam.distance,
            "pan": list(cam.pan)}}
        extractions = [{k: v for k, v in asdict(e).items() if k != "requested"}
                       for e in self.extractions]
        moving = self.clock.interactive_ms
        return {"frames": self.clock.count, "frame_ms_mean": float(times.mean()),
                "frame_ms_p95": float(np.percentile(times, 95)), "state": state,
                "interactive_frames": len(moving),
                "interactive_ms_median": float(np.median(moving)) if moving else None,
                "interactive_ms_last10": [float(v) for v in moving[-10:]],
                "quality": asdict(self.quality),
                "extractions": extractions,
                "bake": bake, "checks": self.checks, "size": list(self._frame_size()),
                "ui": self.ui is not None}

    def close(self) -> None:
        """Stop the workers, save what should be saved, and free the window."""
        self.mesh_worker.close()
        if self.bake is not None:
            self.bake.stop()
        try:
            if self.options.screenshot is not None and self.mesh_stage is not None:
                self.screenshot(self.options.screenshot)
            if self.options.lattice_path is not None and self.shared is not None:
                self.save_lattice(self.options.lattice_path)
            if self.options.stats is not None:
                self.options.stats.write_text(json.dumps(self.figures(), indent=1,
                                                         default=_json_default))
        finally:
            self.uploader = None
            self.renderer.release()
            if self.ui is not None:
                self.ui.close()
            self.window.close()
            if self.shared is not None:
                self.shared.close()


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
