"""The viewer's lazy-bake client: global illumination baked in a separate process.

The lazy baker of `baking.lazy` bakes the texels around the displayed isosurface, visible
ones and those nearest the eye first, a few paths each, then refines; `baking.preview`
first traces paths on the displayed surface itself. A process rather than a thread:
building level scenes (marching cubes again) and the baker's own numpy work hold the GIL
for hundreds of milliseconds. The lattice arrays live in shared memory (`SharedLattice`):
the bake process writes texels and announces them; the viewer's side (`BakeLink`) sends
views and receives the ids of changed texels, which the drawing side re-uploads
(`app.viewer.draw.TexelUploader`). Nothing here touches GL. Messages between the
processes are plain data: a `BakeConfig` crosses as its dict (`BakeConfig.to_dict`, read
back with `from_dict` on arrival), a boundary like a lattice file's.

Length: both ends of one message protocol (the viewer's `BakeLink`, the bake process's
`_BakeProcess`) and the shared arrays they address; split, each message's sender and
receiver would sit in different modules.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.app.allocator import tune_malloc
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.lattice_file import MEMBERS
from isolume.volumes import cores

if TYPE_CHECKING:
    from collections.abc import Sequence
    from multiprocessing.process import BaseProcess
    from multiprocessing.queues import Queue
    from multiprocessing.shared_memory import SharedMemory

    from isolume.baking.lazy import Progress, View
    from isolume.baking.view_texels import LatticeOnFile

PLAN_PREVIEW_PATHS = 64
"""Preview passes of at most this many paths go on while a plan is made (`_plan`)."""
LAZY_SCENES = 4
"""Level scenes the lazy bake caches whatever their size, beside those kept for good
within a quarter of the memory available (`baking.backend.scene_budget`). The texels around one
isosurface use almost every level (their values span the edge profile of the data), so a
lazy bake that revisits them round after round should not rebuild scenes."""


class SharedLattice:
    """A `baking.Lattice` whose arrays live in shared memory blocks.

    The bake process attaches to the same blocks (`attach`) and writes texels; the viewer
    reads them for upload and saving.
    """

    lattice: Lattice
    blocks: list[SharedMemory]
    owner: bool
    relit: np.ndarray

    def __init__(self, lattice: Lattice, blocks: list[SharedMemory], owner: bool,
                 relit: np.ndarray) -> None:
        self.lattice, self.blocks, self.owner = lattice, blocks, owner
        self.relit = relit  # (Z, Y, X) bool: texels showing the turned light's bake

    @staticmethod
    def _layout(geometry, channels: int) -> dict[str, tuple[tuple, str]]:
        shape = tuple(geometry.shape)
        return {"values": ((*shape, channels), "float32"), "samples": (shape, "uint32"),
                "second": (shape, "float32"), "active": (shape, "bool"),
                "preview": ((*shape, channels), "float32"), "preview_paths": (shape, "uint16"),
                "facing": ((*shape, 2), "uint8"), "preview_facing": ((*shape, 2), "uint8"),
                "relit": (shape, "bool")}

    @classmethod
    def create(cls, geometry: LatticeGeometry, channels: int, meta: dict[str, Any],
               source: LatticeOnFile | None = None) -> SharedLattice:
        """New shared arrays, zero or read from the lattice file `source` (a
        `baking.view_texels.LatticeOnFile`, read into them a slab at a time); `meta`: as
        `lattice_meta` describes a lattice (its "config" a dict), or the file's own."""
        from multiprocessing import shared_memory

        arrays, blocks = {}, []
        for name, (shape, dtype) in cls._layout(geometry, channels).items():
            size = max(1, int(np.prod(shape)) * np.dtype(dtype).itemsize)
            block = shared_memory.SharedMemory(create=True, size=size)
            blocks.append(block)
            arrays[name] = np.ndarray(shape, dtype, buffer=block.buf)  # zeros already
        try:
            if source is not None:  # only the file's texels are written: pages as needed
                source.file.read_dense({n: arrays[n] for n in MEMBERS})
        except BaseException:
            for block in blocks:
                block.close()
                block.unlink()
            raise
        meta = dict(meta)
        config = _config(meta.pop("config", None)) or getattr(source, "config", None)
        return cls(_shared_lattice(geometry, arrays, meta, config), blocks, owner=True,
                   relit=arrays["relit"])

    def describe(self) -> dict[str, Any]:
        """What `attach` needs (picklable)."""
        g = self.lattice.geometry
        return {"names": [b.name for b in self.blocks], "shape": list(g.shape),
                "lo": list(g.lo), "hi": list(g.hi), "channels": self.lattice.values.shape[-1],
                "meta": self.lattice.meta,
                "config": self.lattice.config and self.lattice.config.to_dict()}

    @classmethod
    def attach(cls, description: dict[str, Any]) -> SharedLattice:
        """The same arrays, in another process."""
        from multiprocessing import shared_memory

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
        lattice = _shared_lattice(geometry, arrays, dict(description["meta"]),
                                  _config(description["config"]))
        return cls(lattice, blocks, owner=False, relit=arrays["relit"])

    def snapshot(self, relit: bool = False) -> Lattice:
        """A private copy of the lattice (for saving while the bake goes on); `relit`:
        only the texels baked under the turned light (`relit`, read first: the bake
        marks a texel there after its counts), the others as not computed (a lattice
        file holds one light). A texel whose count moved while it was copied (the bake
        process committed it meanwhile) is left out as not computed, rather than saved
        with a count that does not vouch for its mean."""
        lat = self.lattice
        published = self.relit.copy() if relit else None
        samples = lat.samples.copy()
        values, second, facing = lat.values.copy(), lat.second.copy(), lat.facing.copy()
        samples[lat.samples != samples] = 0
        if published is not None:
            samples[~published] = 0
        left_out = samples == 0
        values[left_out], second[left_out], facing[left_out] = 0, 0, 0
        return Lattice(lat.geometry, values, samples, second, lat.active.copy(),
                       json.loads(json.dumps(lat.meta)), config=lat.config, facing=facing)

    def close(self) -> None:
        """Drop the arrays and release (and, as owner, unlink) the blocks."""
        self.lattice = self.relit = None
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


def _shared_lattice(geometry, arrays: dict, meta: dict, config) -> Lattice:
    """The `Lattice` of `SharedLattice._layout`'s `arrays` (shared memory)."""
    return Lattice(geometry, arrays["values"], arrays["samples"], arrays["second"],
                   arrays["active"], meta, preview=arrays["preview"],
                   preview_paths=arrays["preview_paths"], config=config,
                   facing=arrays["facing"], preview_facing=arrays["preview_facing"])


def _config(d: dict | None) -> BakeConfig | None:
    """The `BakeConfig` of a message's config dict (None for None)."""
    return None if d is None else BakeConfig.from_dict(d)


def lattice_meta(volume: volumes.Volume, config: BakeConfig) -> dict[str, Any]:
    """How a bake process is told of a new lattice baked with `config` for `volume`
    (`SharedLattice.create`): the metadata `baking.bake` writes, and the config as a dict
    under "config"."""
    from isolume.baking.lazy import new_lattice

    return dict(new_lattice(volume, config).meta, config=config.to_dict())


TRACED = ("rays_traced", "trace_seconds", "scene_seconds", "bake_seconds")
"""What `Traced` counts: the metadata's "stats" of a bake (`baking.bake`), but its paths."""


class Traced:
    """The rays and seconds the lazy bake spent on the lattice it bakes now, for that
    lattice's metadata: counted as the Baker's counters grow (`baking.backend.BakeStats`,
    one Baker's since its plan, turns of the light included) and as `serve`'s seconds in
    batches do (one loop's), and counted from zero again for a turned light's lattice.

    Attributes:
        totals: the counts of `TRACED` so far.
    """

    def __init__(self, previous: dict[str, Any]) -> None:
        """`previous`: the lattice's "stats" before this bake (a file's), or {}."""
        self.totals: dict[str, float] = {k: previous.get(k, 0) for k in TRACED}
        self._baker: Any = None  # the Baker whose counters `_seen` holds
        self._seen: dict[str, float] = dict.fromkeys(TRACED, 0)

    def new_loop(self, baker: Any) -> None:
        """A `serve` loop of `baker` starts (its seconds from zero; a new Baker's
        counters too)."""
        if baker is not self._baker:
            self._baker, self._seen = baker, dict.fromkeys(TRACED, 0)
        self._seen["bake_seconds"] = 0.0

    def count(self, serve_seconds: float | None = None) -> None:
        """Add what the Baker of the loop and the loop (`serve_seconds` in batches so far;
        None: as at the last count, within a batch) did since the last count."""
        if serve_seconds is None:
            serve_seconds = self._seen["bake_seconds"]
        now = _counters(self._baker, serve_seconds)
        for key in TRACED:
            self.totals[key] += now[key] - self._seen[key]
        self._seen = now

    def restart(self) -> None:
        """A turned light's lattice: nothing traced into it yet (what the Baker did so far
        was for the light before)."""
        self.totals = dict.fromkeys(TRACED, 0)
        if self._baker is not None:
            self._seen = _counters(self._baker, 0.0)


def _counters(baker: Any, serve_seconds: float) -> dict[str, float]:
    """The `TRACED` counts of `baker` (a `baking.bake.Baker`) and a loop's seconds."""
    stats = baker.stats
    return {"rays_traced": int(stats.rays), "trace_seconds": float(stats.trace_seconds),
            "scene_seconds": float(stats.scene_seconds), "bake_seconds": float(serve_seconds)}


def traced_meta(lattice: Lattice, traced: dict[str, float]) -> dict[str, Any]:
    """The metadata that says what was traced into `lattice` (`Traced.totals`, its paths
    the samples it holds), as `baking.bake` records a bake's: "stats" and its rays and
    trace seconds beside it."""
    stats = {"paths": int(lattice.samples.sum(dtype=np.int64)), **traced}
    return {"stats": stats, "rays_traced": int(traced["rays_traced"]),
            "trace_seconds": float(traced["trace_seconds"])}


def _bake_main(job: dict, inbox, outbox) -> None:
    """Entry point of the bake process: previews for the first view, the plan (while the
    previews go on and later views get theirs), then `baking.lazy.serve` until stopped."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the viewer's to handle
    tune_malloc()
    try:
        os.nice(19)  # idle priority: the viewer (and llvmpipe's threads) come first
    except (AttributeError, OSError):
        pass
    process = None
    try:
        cores.use(job["workers"])  # --bake-workers: the plan's kernels, Embree, BLAS too
        process = _BakeProcess(job, inbox, outbox)
        process.run()
    except Exception as exc:
        outbox.put(("error", f"{exc.__class__.__name__}: {exc}"))
    finally:
        if process is not None:
            process.shared.close()


class _BakeProcess:
    """The lazy bake's side of the link (runs in the spawned process).

    A turned light (a `baking.lazy.View` whose ``light`` differs from the one baked) makes
    the bake go on under the new light into a lattice of its own (`baking.lazy.Relight`),
    keeping the plan and the level scenes: its previews and rounds follow the same order
    (visible texels, then the rest of the surface), and each texel's new estimate replaces
    the old one on screen once it rests on enough paths. Turning again drops that work and
    starts over for the last direction."""

    def __init__(self, job: dict, inbox, outbox) -> None:
        import multiprocessing

        from isolume.baking.lazy import turned_light
        from isolume.baking.preview import Previewer

        self.job, self.inbox, self.outbox = job, inbox, outbox
        self.shared = SharedLattice.attach(job["lattice"])
        self.parent = multiprocessing.parent_process()
        self.volume = volumes.Volume(**self._first(inbox))
        self.config = _config(job["config"])  # the light and range baked now
        self.workers = job["workers"] or cores.threads()
        self.previewer = Previewer(self.volume, self.config, self.shared.lattice,
                                   self.workers)
        self.lit = None  # the last view given its first preview pass (held: not an id)
        self.waiting: list = []  # messages for `serve`, in order
        self.light = turned_light(self.config)  # None: nothing a viewer can turn
        self.relight = None  # the `baking.lazy.Relight` of the last turn, if any
        self.scheduler = None  # of the loop running now
        self.relit_previews = 0
        self.traced = Traced(self.shared.lattice.meta.get("stats", {}))

    def _first(self, inbox) -> dict:
        """The volume's fields, the first message `BakeLink` sends; RuntimeError when the
        viewer's process ends before sending them."""
        import queue

        while True:
            try:
                return inbox.get(timeout=1.0)[1]
            except queue.Empty:
                if self.parent is not None and not self.parent.is_alive():
                    raise RuntimeError("the viewer ended before it sent the volume") from None
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

    def turned(self, view) -> bool:
        """Whether `view` shows the light turned away from the one baked now."""
        from isolume.baking.lazy import same_direction

        return (view.light is not None and self.light is not None
                and not same_direction(view.light, self.light))

    def turn(self, view) -> None:
        """Bake under the light of `view` from now on if it was turned: a new
        `baking.lazy.Relight` (the work of an earlier turn is dropped), previews traced
        again under the new light."""
        from isolume.baking.lazy import Relight, relit_config
        from isolume.baking.preview import Previewer

        if not self.turned(view):
            return
        self.config = relit_config(self.config, view.light)
        self.relight = Relight(self.shared.lattice, self.config, self.shared.relit)
        only_active = self.previewer.only_active
        self.previewer = Previewer(self.volume, self.config, self.relight.fresh, self.workers)
        self.previewer.only_active = only_active
        self.light, self.lit = self.relight.direction, None
        self.relit_previews = 0  # paths of the largest preview pass done under it
        self.traced.restart()
        self.outbox.put(("relight", {"direction": [float(v) for v in self.light],
                                     "config": self.config.to_dict()}))
        self.outbox.put(("traced", dict(self.traced.totals)))

    def first_light(self, view) -> None:
        """The first preview pass of `view` (a few paths per visible texel, traced on its
        displayed surface); the others follow through `preview_step`."""
        if view is self.lit or view.visible is None or not len(view.visible):
            return
        self.lit, self.relit_previews = view, 0
        self._announce(self.previewer.set_view(view.iso, view.visible, view.eye,
                                               view.points))

    def preview_step(self) -> bool:
        """A slice of the queued preview passes; False when there was none (or when the
        lattice goes first, `lattice_first`)."""
        if not self.previewer.busy or self.lattice_first():
            return False
        self._announce(self.previewer.step())
        return True

    def lattice_first(self) -> bool:
        """Under a turned light, once a preview pass put the visible texels it reaches on
        screen (`RELIGHT_PATHS` paths), the visible rounds of the lattice up to that many
        paths go before the further preview passes: they also reach the texels no preview
        does (a start point inside a thin feature), which would otherwise keep the old
        light for the 256-path pass (15 s on the engine CT)."""
        from isolume.baking.lazy import RELIGHT_PATHS

        if self.relight is None or self.scheduler is None or self.relit_previews < RELIGHT_PATHS:
            return False
        stage = self.scheduler.progress().stage
        return stage is not None and stage[0] == "visible" and stage[1] <= RELIGHT_PATHS

    def _announce(self, flat: np.ndarray) -> None:
        """Tell the viewer which texels changed, and which preview passes finished."""
        self._texels(flat)
        while self.previewer.done:
            done = self.previewer.done.pop(0)
            if self.relight is not None:
                self.relit_previews = max(self.relit_previews, done["paths"])
            self.outbox.put(("preview", done))
        self._relit_status()

    def _texels(self, flat: np.ndarray) -> None:
        """Announce the texels `flat` changed in the lattice baked now (under a turned
        light: those of them put on screen, `Relight.publish`)."""
        if self.relight is not None:
            flat = self.relight.publish(flat)
        if len(flat):
            self.outbox.put(("texels", flat))

    def _send(self, message: tuple) -> None:
        """`serve`'s messages to the viewer (texels through `_texels`), each commit and
        report followed by what was traced into the lattice so far (`_report_traced`)."""
        if message[0] == "texels":
            self._texels(message[1])
            self._report_traced()
            return
        self.outbox.put(message)
        if message[0] == "progress":
            self._report_traced(message[2]["seconds"])
            self._relit_status()

    def _report_traced(self, serve_seconds: float | None = None) -> None:
        """Count what the bake traced since the last count (`Traced.count`) and tell the
        viewer the totals, as ``("traced", dict)``."""
        self.traced.count(serve_seconds)
        self.outbox.put(("traced", dict(self.traced.totals)))

    def _relit_status(self) -> None:
        """How far the view is on screen under the turned light, as ``("relit", dict)``."""
        if self.relight is not None and self.scheduler is not None:
            self.outbox.put(("relit", self.relight.status(self.scheduler)))

    def _keep(self, message) -> bool:
        """Queue `message` for `serve`, lighting views at once; False on "stop"."""
        from isolume.baking.lazy import View

        if message == "stop":
            return False
        if isinstance(message, View):
            self.turn(message)
            self.first_light(message)
        self.waiting.append(message)
        return True

    def _plan(self, config):
        """Make the Baker for `config` on a thread; meanwhile every new view gets its
        preview passes up to `PLAN_PREVIEW_PATHS` paths (the picture within 1.2× of the
        fully baked error), and the further passes wait: the plan takes seconds, they take
        tens (CThead: the plan was ready after 29 s with every pass going on beside it).
        Its stages are reported as ``("planning", stage)``. None when told to stop."""
        import threading

        from isolume.baking.backend import scene_budget
        from isolume.baking.bake import Baker

        made: dict = {"memory": scene_budget()}

        def planning(stage: str, fraction: float | None = None) -> None:
            self.outbox.put(("planning", stage if fraction is None
                             else f"{stage} {fraction:.0%}"))

        def make() -> None:
            try:
                made["baker"] = Baker(self.volume, config, lattice=self.shared.lattice,
                                      workers=self.job["workers"], scene_cache=LAZY_SCENES,
                                      scene_memory=made["memory"], progress=planning)
            except BaseException as exc:  # re-raised below, in this thread
                made["error"] = exc

        planner = threading.Thread(target=make, name="isolume-plan", daemon=True)
        planner.start()
        while planner.is_alive():
            paths = self.previewer.next_paths
            beside = paths is not None and paths <= PLAN_PREVIEW_PATHS
            if beside:
                self.preview_step()
            message = self.receive_within(None if beside else 0.1)
            if message is not None and not self._keep(message):
                return None
        if "error" in made:
            raise made["error"]
        return made["baker"], made["memory"]

    def run(self) -> None:
        from isolume.baking.lazy import View, view_iso_range
        from isolume.baking.preview import warm_up as preview_warm_up

        preview_warm_up(self.volume)  # while the viewer opens its window
        self.outbox.put(("started", {"seconds": time.time() - self.job["started"]}))
        self.previewer.prepare(self.job["iso"])  # while it makes its first surface
        message = self.receive(True)  # the first view gets its first preview before the plan
        while not isinstance(message, View):
            if not self._keep(message):
                return
            message = self.receive(True)
        self._keep(message)
        old_plan = None
        if self.job["follow_iso"]:  # a fresh lattice: bake for the isovalues around the view
            self.config = dataclasses.replace(
                self.config, iso_range=view_iso_range(self.volume, message.iso))
        while True:
            plan = self._serve(old_plan)
            if plan is None:
                return
            outside = self.waiting[0]  # the view the plan does not serve
            self.turn(outside)
            self.first_light(outside)  # its previews go on while the new plan is made
            self.config = dataclasses.replace(
                self.config, iso_range=view_iso_range(self.volume, outside.iso))
            old_plan = plan
            self.outbox.put(("replanning", {"iso": outside.iso}))

    def _serve(self, old_plan):
        """Plan for `self.config` (keeping what the lattice holds for `old_plan` that the
        new plan can use) and bake lazily, under each turned light in turn. Returns the
        plan when a view outside its iso range ended the loop (that view first in
        `waiting`), None when told to stop."""
        baker = self._baker(old_plan)
        if baker is None:
            return None
        try:
            while True:
                stats = self._serve_light(baker)
                if stats.outside is None:
                    return None
                self.waiting.insert(0, stats.outside)
                if not self._inside(baker.plan, stats.outside):
                    return baker.plan
                self.turn(stats.outside)  # the same plan and level scenes, a new light
        finally:
            baker.close()

    def _inside(self, plan, view) -> bool:
        """Whether `plan` serves the isovalue of `view` (a lattice from a file serves every
        one: the panel warns outside its range)."""
        lo, hi = plan.iso_range
        return not self.job["follow_iso"] or lo <= view.iso <= hi

    def _baker(self, old_plan):
        """The Baker of `self.config` (`_plan`), the lattice carried over from `old_plan`
        (`baking.lazy.carry_over`: the baked one and a turned light's), the plan announced
        as ``("ready", ...)``; None when told to stop."""
        from isolume.baking.lazy import carry_over
        from isolume.baking.preview import drop_inactive

        t0 = time.perf_counter()
        lattice = self.shared.lattice
        active = lattice.active  # the Baker replaces the lattice's attribute
        if old_plan is not None:  # new levels: the Baker would keep the lattice's
            lattice.meta.pop("plan", None)
        lattice.config = self.config  # what a saved lattice was baked with
        made = self._plan(self.config)
        if made is None:
            return None
        baker, scene_memory = made
        relight = self.relight
        if old_plan is not None:
            reset = carry_over(lattice, old_plan, baker.plan)
            if relight is not None:  # and the turned light's: published texels follow it
                carry_over(relight.fresh, old_plan, baker.plan)
                reset = np.union1d(reset, relight.publish(np.flatnonzero(relight.published)))
            if len(reset):
                self.outbox.put(("texels", reset))
        active[...] = baker.plan.active
        baker.lattice.active = active
        if relight is not None:
            relight.fresh.active = active
        self.previewer.only_active = True
        stale = drop_inactive(lattice)
        if relight is not None:
            self._texels(drop_inactive(relight.fresh))
        if len(stale):
            self.outbox.put(("texels", stale))
        lattice.config = self.config  # (a turn during the plan)
        self.outbox.put(("ready", {"seconds": time.perf_counter() - t0,
                                   "active": len(baker.plan.ids),
                                   "levels": len(baker.plan.levels),
                                   "scene_memory": scene_memory, "meta": baker.lattice.meta,
                                   "config": baker.lattice.config.to_dict()}))
        return baker

    def _serve_light(self, baker):
        """`baking.lazy.serve` under the light baked now (into the turned light's lattice
        after a turn) until told to stop or a view it does not serve (another isovalue
        range, a turned light) ends it; returns serve's stats."""
        from isolume.baking.lazy import LAZY_TARGET_ERROR, LazyScheduler, serve

        if self.relight is not None and baker.lattice is not self.relight.fresh:
            baker.relight(self.config, self.relight.fresh)
        self.traced.new_loop(baker)
        self.scheduler = LazyScheduler(baker.plan, baker.geometry,
                                       baker.lattice.samples.reshape(-1),
                                       max_samples=self.config.samples,
                                       batch_paths=self.job["batch_paths"],
                                       judged_by=baker,
                                       target_error=self.config.target_error
                                       or LAZY_TARGET_ERROR)

        def receive(block: bool):
            return self.waiting.pop(0) if self.waiting else self.receive(block)

        return serve(baker, self.scheduler, receive, self._send, on_view=self.first_light,
                     before_batch=self.preview_step,
                     accepts=lambda view: (self._inside(baker.plan, view)
                                           and not self.turned(view)))


def range_warning(meta: dict[str, Any], iso: float) -> tuple[str, ...]:
    """A panel line when `iso` lies outside the iso range of the lattice whose metadata is
    `meta` (its texels are lit on surfaces inside it); () otherwise."""
    from isolume.baking.plan import served_range

    served = served_range(meta)
    if served is None or served[0] <= iso <= served[1]:
        return ()
    return (f"WARNING: iso {iso:.4g} is outside the baked range {served[0]:.4g} to "
            f"{served[1]:.4g}: light of the surface at the range's end",)


def stop_process(process: Any, inbox: Any, outbox: Any, receive: Callable[[], object],
                 timeout: float) -> None:
    """Ask a worker `process` to finish and exit ("stop" on its `inbox`), calling
    `receive` (which reads its `outbox`) while it winds down — a process whose queue
    holds more than its pipe takes cannot exit until that is read — and terminate it if
    it has not ended after `timeout` seconds (at once for 0: it has written nothing);
    then close both queues."""
    if process.is_alive() and timeout > 0:
        inbox.put("stop")
        deadline = time.perf_counter() + timeout
        while process.is_alive() and time.perf_counter() < deadline:
            process.join(0.05)
            receive()
    if process.is_alive():
        process.terminate()
        process.join(2)
    for q in (inbox, outbox):
        q.cancel_join_thread()
        q.close()


class BakeLink:
    """The viewer's side of the lazy bake process: send views, receive committed texels."""

    inbox: Queue[Any]
    outbox: Queue[Any]
    process: BaseProcess
    previews: list[tuple[float, dict[str, Any]]]
    warm: dict[str, Any] | None
    light_baked: tuple[float, ...] | None
    turns: list[dict[str, Any]]

    def __init__(self, volume: volumes.Volume, config: BakeConfig, shared: SharedLattice,
                 workers: int | None, iso: float, batch_paths: int | None = None,
                 follow_iso: bool = False) -> None:
        import multiprocessing

        from isolume.baking.lazy import BATCH_PATHS

        ctx = multiprocessing.get_context("spawn")
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self.inbox.cancel_join_thread()  # a process gone unread leaves no exit waiting
        job = {  # small: the process's arguments go through a pipe its start waits on
            "lattice": shared.describe(),
            "config": config.to_dict(), "workers": workers, "iso": float(iso),
            "batch_paths": batch_paths or BATCH_PATHS, "started": time.time(),
            "follow_iso": follow_iso,
        }
        self.started: float = time.perf_counter()
        self.process = ctx.Process(target=_bake_main, args=(job, self.inbox, self.outbox),
                                   name="isolume-bake", daemon=True)
        self.process.start()
        # the volume's samples go by the queue, whose thread writes them: the start writes
        # its arguments itself and, with the child gone before reading them (a script
        # without a main guard, which the child imports again), would wait for ever
        self.inbox.put(("volume", {
            "data": volume.data, "spacing": volume.spacing, "origin": volume.origin,
            "name": volume.name, "source": volume.source,
            "suggested_iso": volume.suggested_iso}))
        self.ready: dict[str, Any] | None = None
        self.ready_config: BakeConfig | None = None  # the config of the last "ready"
        self.progress: Progress | None = None
        self.stats: dict[str, Any] = {}
        self.error: str | None = None
        self.paused: bool = False
        self.paused_ack: bool = False
        self.history: list[tuple[float, object]] = []
        self.previews = []  # (seconds since start, figures) per pass
        self.warm = None  # the process is ready for views (its start-up time)
        self.planning: tuple[float, str] = (self.started, "")  # since when, which stage
        self.replans: int = 0
        from isolume.baking.lazy import turned_light

        baked = turned_light(config)  # the light the lattice was baked with, if turnable
        self.light_baked = None if baked is None else tuple(float(v) for v in baked)
        self.light_sent: tuple[float, ...] | None = self.light_baked  # that of the last view sent
        self.turns = []  # per turned light: direction, seconds to each stage
        self.relit: dict[str, Any] | None = None  # the last turned light's progress on screen
        self.relit_config: BakeConfig | None = None  # the config it is baked with
        self.traced: dict[str, float] | None = None  # `Traced.totals` of the lattice baked

    def send_view(self, view: View) -> None:
        from isolume.baking.lazy import same_direction

        if view.light is not None and (self.light_sent is None
                                       or not same_direction(view.light, self.light_sent)):
            self.turns.append({"direction": list(view.light), "sent": time.perf_counter()})
            self.light_sent = view.light
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
                self.ready, self.ready_config = message[1], _config(message[1]["config"])
                if self.relit_config is not None:  # planned again under the turned light
                    self.relit_config = self.ready_config
            elif kind == "planning":
                self.planning = (self.planning[0], message[1])
            elif kind == "replanning":  # the view left the baked iso range
                self.ready, self.progress = None, None
                self.planning = (time.perf_counter(), "")
                self.replans += 1
            elif kind == "paused":
                self.paused_ack = message[1]
            elif kind == "started":
                self.warm = message[1]
            elif kind == "preview":
                self.previews.append((time.perf_counter() - self.started, message[1]))
            elif kind == "relight":  # the bake goes on under a turned light, in a new lattice
                self.relit_config, self.relit = _config(message[1]["config"]), None
                self.progress = None  # the old light's: its "progress" comes next
                self._turn_event(message[1]["direction"], "started_s")
            elif kind == "traced":
                self.traced = message[1]
            elif kind == "relit":
                self.relit = message[1]
                self._turn_progress(message[1])
            elif kind == "error":
                self.error = message[1]
        if self.error is None and self.ready is None and not self.process.is_alive():
            self.error = _ended(self.process.exitcode)
        return texels

    def _turn_event(self, direction, stage: str) -> None:
        """Note the seconds from sending the view with the light turned to `direction`
        until `stage` (once per stage)."""
        from isolume.baking.lazy import same_direction

        for turn in reversed(self.turns):
            if same_direction(turn["direction"], direction):
                turn.setdefault(stage, time.perf_counter() - turn["sent"])
                return

    def _turn_progress(self, status: dict) -> None:
        """Note when half, 90 %, 99 % and all of the visible texels, then the whole
        surface, show the turned light."""
        done = status["visible_done"] / max(status["visible"], 1)
        for share in (50, 90, 99):
            if status["visible"] and done >= share / 100:
                self._turn_event(status["direction"], f"visible_{share}_s")
        if status["visible"] and status["visible_done"] == status["visible"]:
            self._turn_event(status["direction"], "visible_s")
        if status["surface"] and status["surface_done"] == status["surface"]:
            self._turn_event(status["direction"], "surface_s")

    def relit_fraction(self, direction: Sequence[float] | np.ndarray) -> float | None:
        """Share of the visible texels (of the surface texels when none is known) that
        show the bake under the light turned to `direction` (3,); None when the bake
        reports no progress under that light; 1 when it is the light baked and was
        never turned."""
        from isolume.baking.lazy import same_direction

        r = self.relit
        if self.relit_config is None and self.light_baked is not None and same_direction(
                self.light_baked, direction):
            return 1.0  # never turned: nothing to re-bake
        if r is None or not same_direction(r["direction"], direction):
            return None
        if r["visible"]:
            return r["visible_done"] / r["visible"]
        return r["surface_done"] / r["surface"] if r["surface"] else None

    def relit_line(self, direction: Sequence[float] | np.ndarray, name: str) -> str | None:
        """The panel's line on the bounced light of the `name` ("sun", "light") turned to
        `direction` (3,), or None when the bake has not started on that light."""
        from isolume.baking.lazy import same_direction

        r = self.relit
        if self.light_sent is None or not same_direction(self.light_sent, direction):
            return None  # not sent yet (the light is moving)
        if self.relit_config is None and (self.light_baked is None
                                          or same_direction(self.light_baked, direction)):
            return None  # never turned
        if r is None or not same_direction(r["direction"], direction):
            return f"Bounced light: re-baking for the turned {name}..."
        if r["visible"] and r["visible_done"] < r["visible"]:
            return (f"Bounced light: re-baking for the turned {name}, "
                    f"{100 * r['visible_done'] / r['visible']:.0f} % of the visible texels")
        if r["surface_done"] < r["surface"]:
            return (f"Bounced light: up to date with the turned {name} where visible; "
                    f"{100 * r['surface_done'] / r['surface']:.0f} % of the surface")
        return f"Bounced light: up to date with the turned {name}."

    def snapshot(self, shared: SharedLattice) -> Lattice:
        """A copy of `shared` to save, with the bake's metadata: after a turn, only the
        texels baked under the turned light, with its config (a file holds one light);
        its "stats" what was traced into it (`traced_meta`: the paths it holds, the rays
        and seconds of its own bake, since the turn)."""
        relit = self.relit_config is not None
        lattice = shared.snapshot(relit=relit)
        if self.ready is not None:
            lattice.meta.update(self.ready["meta"])
            lattice.config = self.ready_config
        if relit:
            lattice.config = self.relit_config
        if self.traced is not None:
            lattice.meta.update(traced_meta(lattice, self.traced))
        return lattice

    def on_light(self, direction: Sequence[float] | np.ndarray) -> bool:
        """Whether the bake works under the light turned to `direction` (3,) now: the light
        of its last turn, or the one baked when never turned (or none can turn)."""
        from isolume.baking.lazy import same_direction, turned_light

        baking = (self.light_baked if self.relit_config is None
                  else turned_light(self.relit_config))
        return baking is None or same_direction(baking, direction)

    def gi_received(self, iso: float) -> bool:
        """Whether light for `iso` has arrived: a preview pass of it, or estimates of
        every visible texel of its surface (some texels near it are not enough: the
        rest of the view would still be dark)."""
        p = self.progress
        return (any(done["iso"] == iso for _, done in self.previews)
                or (p is not None and p.iso == iso and p.visible_fraction >= 1.0))

    def near_fraction(self, iso: float) -> float | None:
        """Fraction of the texels near the surface at `iso` that have an estimate (None:
        no progress reported for that isovalue yet)."""
        p = self.progress
        return p.near_fraction if p is not None and p.iso == iso else None

    def status(self, iso: float) -> tuple[tuple[float, float] | None, tuple[str, ...]]:
        """What the panel shows: ((visible, surface) fractions done or None, lines)."""
        if self.error:
            return None, (f"error: {self.error}",)
        preview = self._preview_line(iso)
        if self.ready is None:
            since, stage = self.planning
            stage = f" ({stage})" if stage else ""
            return None, (f"planning the bake{stage}... {time.perf_counter() - since:.0f} s",
                          preview)
        p, s = self.progress, self.stats
        if p is None:
            return None, ("waiting for the surface", preview)
        stage = "done for this view" if p.stage is None else f"{p.stage[0]} to {p.stage[1]} paths"
        if p.surface == 0:
            stage = "this isovalue lies outside the baked range"
        rate = s.get("paths", 0) / max(s.get("seconds", 0.0), 1e-9)
        lines = (preview, f"{stage}, {rate:,.0f} paths/s",
                 f"{p.visible:,} visible / {p.surface:,} surface texels")
        meta = self.ready.get("meta", {})
        return (p.visible_fraction, p.surface_fraction), range_warning(meta, iso) + lines

    def _preview_line(self, iso: float) -> str:
        """The last preview pass done for the isovalue `iso` ("" when none)."""
        done = [f for _, f in self.previews if f["iso"] == iso]
        return f"preview: {done[-1]['paths']} paths/texel on this surface" if done else ""

    def stop(self, timeout: float = 15.0) -> None:
        """Ask the process to finish its batch and exit, receiving what it still sends
        meanwhile (a process whose queue holds more than its pipe takes cannot exit until
        that is read); terminate it if it has not ended after `timeout` seconds (at once
        while it is still planning: it has written nothing yet)."""
        self.poll()
        stop_process(self.process, self.inbox, self.outbox, self.poll,
                     timeout if self.ready is not None else 0.0)


def _ended(exitcode: int | None) -> str:
    """What the viewer says of a bake process that ended with `exitcode` before its plan
    was ready; from a script (a ``__main__`` with a file), how the usual cause is
    mended: the process starts by importing the script again, and a top level that is
    not under a main guard runs again there and cannot start processes."""
    said = f"the bake process ended (exit code {exitcode})"
    if exitcode and getattr(sys.modules.get("__main__"), "__file__", None):
        said += ("; a script that shows a view keeps its top level under "
                 "`if __name__ == \"__main__\":` (the bake process imports it again)")
    return said

