"""The napari plugin's background lighting: global illumination of the shown isosurface,
traced in a separate process and refined pass by pass.

The light is ``isolume export``'s without a lattice (`app.export_light.surface_radiance`):
the texels the vertices' lookups read get paths traced on the isosurface itself, then the
side-aware lookup, plus the sky's sun and the lights the lattice leaves to the pixels,
through Embree shadow rays. Each pass
traces `PREVIEW_PATHS` and then the requested samples, from scratch: path k of a texel
is the same random path in every pass (the generator is keyed by texel and path), so the
last pass is export's light exactly.

A process rather than a thread: marching cubes, the Embree scene's build and the numpy
glue between the traced chunks hold the GIL, which would stall napari's UI thread. The
process runs at idle priority on `cores.threads()` threads; napari's side (`LightingLink`)
sends requests and polls for the results, never blocking. Messages are plain data: a
request is a dict whose ``config`` is `BakeConfig.to_dict`; the process answers

* ``("mesh", id, vertices, faces, areas)``: the isosurface of request `id`: (V, 3) world
  x, y, z float32, (F, 3) int32 triangles counter-clockwise seen from the lit side, (V,)
  float64 a third of the area of the triangles around each vertex (world units²);
* ``("light", id, paths, radiance)``: (V, 3) float64 linear outgoing radiance after a pass
  of `paths` paths per texel;
* ``("empty", id, message)``: no surface at that isovalue;
* ``("error", id, message)``: the request failed (one line).
"""

from __future__ import annotations

import os
import queue
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume import volumes
from isolume.volumes import cores

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess
    from multiprocessing.queues import Queue

    from isolume.baking.config import BakeConfig
    from isolume.baking.trace import Scene

PREVIEW_PATHS = (4, 16)
"""Paths per texel of the passes shown before the requested samples (those below them)."""
PARENT_CHECK_S = 0.5
"""Seconds between the process's checks that napari is still there, while idle."""
STOP_WAIT_S = 5.0
"""Seconds `LightingLink.close` waits for the process to end before terminating it."""


def pass_paths(samples: int) -> list[int]:
    """The paths per texel of each pass for `samples` requested: the `PREVIEW_PATHS`
    below it, then `samples` itself (e.g. 64 → [4, 16, 64]; 8 → [4, 8])."""
    return [p for p in PREVIEW_PATHS if p < samples] + [int(samples)]


def volume_job(volume: volumes.Volume) -> dict[str, Any]:
    """The picklable fields of `volume` that the process rebuilds it from."""
    return {"data": volume.data, "spacing": volume.spacing, "origin": volume.origin,
            "name": volume.name, "source": volume.source,
            "suggested_iso": volume.suggested_iso}


def traced_radiance(volume: volumes.Volume, config: BakeConfig, iso: float, mesh: volumes.Mesh,
                    scene: Scene, workers: int, direct: dict | None = None) -> np.ndarray:
    """(V, 3) linear outgoing radiance (irradiance units / sr) at `mesh`'s vertices, as
    ``isolume export`` lights them without a lattice: global illumination traced with
    `config.samples` paths per texel, plus the per-pixel lights through shadow rays.

    Args:
        config: `baking.config.BakeConfig` of the lighting (`app.options.view_light`).
        mesh: the isosurface ρ = `iso` (world x, y, z); scene: its `baking.trace.Scene`.
        workers: tracing threads.
        direct: `export_light.surface_radiance`'s keeper of the direct light, for passes
            on the same mesh.
    """
    from isolume.app.export_light import surface_radiance

    radiance, _, _ = surface_radiance(volume, iso, mesh, scene, None, config, config.albedo,
                                      workers=workers, direct=direct)
    return radiance


class _Surfaces:
    """The isosurface of the last (isovalue, normals, flip) asked for, its Embree scene,
    its vertex areas and its direct light, kept while only the light changes; `sent`:
    whether napari has been sent that mesh."""

    def __init__(self, volume: volumes.Volume) -> None:
        self.volume, self.key, self.value = volume, None, None
        self.sent = False
        self.direct: dict = {}

    def get(self, iso: float, normals: str, flip: bool):
        """(mesh, scene, areas) of the surface ρ = `iso`; mesh is None (and scene its
        message) when there is none."""
        key = (float(iso), normals, bool(flip))
        if key != self.key:
            self.key, self.value = key, self._build(*key)
            self.sent = False
            self.direct.clear()
        return self.value

    def _build(self, iso: float, normals: str, flip: bool):
        from isolume.app.export_files import vertex_areas
        from isolume.baking.trace import Scene

        mesh = volumes.isosurface(self.volume, iso, normals=normals, flip_normals=flip)
        if mesh.empty:
            return None, mesh.message, None
        if flip:  # triangles counter-clockwise seen from the normals' side, as export
            mesh = replace(mesh, faces=np.ascontiguousarray(mesh.faces[:, ::-1]))
        return mesh, Scene(mesh.vertices, mesh.faces), vertex_areas(mesh.vertices, mesh.faces)


def serve(job: dict[str, Any], inbox: Queue[Any], outbox: Queue[Any]) -> None:
    """Entry point of the lighting process: light each request in turn until "stop" (or
    until napari's process is gone), a newer request cutting the passes short."""
    import multiprocessing
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is napari's
    try:
        os.nice(19)  # idle priority: napari's UI thread and the GL driver come first
    except (AttributeError, OSError):
        pass
    workers = cores.use(job["workers"])
    surfaces = _Surfaces(volumes.Volume(**job["volume"]))
    parent = multiprocessing.parent_process()
    request = _next_request(inbox, parent, block=True)
    while request is not None:
        try:
            request = _light(surfaces, request, workers, inbox, parent, outbox)
        except Exception as exc:  # reported to napari, which shows it; the process goes on
            outbox.put(("error", request["id"], f"{exc.__class__.__name__}: {exc}"))
            request = _next_request(inbox, parent, block=True)


def _light(surfaces: _Surfaces, request: dict, workers: int, inbox, parent, outbox):
    """Send the mesh of `request` and its light pass by pass; returns the next request
    (a newer one that arrived meanwhile, else the next to come) or None to stop."""
    from isolume.baking.config import BakeConfig

    config = BakeConfig.from_dict(request["config"])
    iso = request["iso"]
    mesh, scene, areas = surfaces.get(iso, config.normals, config.flip_normals)
    if mesh is None:
        outbox.put(("empty", request["id"], scene))
        return _next_request(inbox, parent, block=True)
    if surfaces.sent:  # napari holds it: the key alone
        outbox.put(("mesh", request["id"], surfaces.key))
    else:
        outbox.put(("mesh", request["id"], surfaces.key, np.asarray(mesh.vertices, np.float32),
                    np.asarray(mesh.faces, np.int32), areas))
        surfaces.sent = True
    for paths in pass_paths(config.samples):
        newer = _next_request(inbox, parent, block=False)
        if newer is not False:
            return newer
        radiance = traced_radiance(surfaces.volume, replace(config, samples=paths), iso,
                                   mesh, scene, workers, surfaces.direct)
        outbox.put(("light", request["id"], paths, radiance))
    return _next_request(inbox, parent, block=True)


def _next_request(inbox, parent, block: bool):
    """The newest request waiting (older ones are dropped); None for "stop" or when
    napari's process is gone; False when none waits and not `block`."""
    latest = False
    while True:
        try:
            message = inbox.get(block=block and latest is False, timeout=PARENT_CHECK_S)
        except queue.Empty:
            if latest is not False or not block:
                return latest
            if parent is not None and not parent.is_alive():
                return None
            continue
        if message == "stop":
            return None
        latest = message


class LightingLink:
    """napari's side of the lighting process of one volume: `send` requests, `poll` for
    the results; neither blocks."""

    inbox: Queue[Any]
    outbox: Queue[Any]
    process: BaseProcess

    def __init__(self, volume: volumes.Volume, workers: int | None = None) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")  # no fork of a process running Qt
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        job = {"volume": volume_job(volume), "workers": workers}
        self.process = ctx.Process(target=serve, args=(job, self.inbox, self.outbox),
                                   name="isolume-napari-light", daemon=True)
        self.process.start()

    def send(self, request: dict[str, Any]) -> None:
        """Ask for the light of `request` (id, iso, config as a dict); it replaces any
        request not yet started."""
        self.inbox.put(request)

    def poll(self) -> list[tuple[Any, ...]]:
        """The messages that arrived (module docs), oldest first; an ``("error", None,
        message)`` when the process has died."""
        messages = []
        while True:
            try:
                messages.append(self.outbox.get_nowait())
            except queue.Empty:
                break
        if not messages and not self.process.is_alive():
            messages.append(("error", None, "the lighting process ended (exit code "
                                            f"{self.process.exitcode})"))
        return messages

    def close(self) -> None:
        """Stop the process, dropping the results it still sends meanwhile (terminated
        after `STOP_WAIT_S` seconds if it does not end: `bake_client.stop_process`)."""
        from isolume.app.viewer.bake_client import stop_process

        stop_process(self.process, self.inbox, self.outbox, self.poll, STOP_WAIT_S)
