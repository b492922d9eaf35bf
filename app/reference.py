"""``isolume reference``: a path-traced reference image of the displayed isosurface.

Same camera as ``isolume render`` (`app.render.renderer.framed_camera`, pixel-centre rays from
`Camera.primary_rays`), same lighting as ``isolume bake`` (the baker's integrator). Writes

* ``FILE.exr``: linear radiance (``RGB``), its per-pixel standard error (``stderr.R/G/B``)
  and the surface ``mask`` (1 where the primary ray hits the isosurface, 0 elsewhere;
  there ``RGB`` is the environment seen along the ray, or black);
* ``FILE.json``: spp, seconds, rays, camera, bake configuration, summary statistics;
* ``FILE.state.npz``: per-pixel sample count, sum and centred sum of squares. Running the
  same command again with a larger ``--spp`` adds samples (exact statistics); Ctrl-C saves
  what is done. Another camera, volume or lighting with the same ``--out`` is an error.

The image is deterministic: the same seed gives the same bits with any ``--workers``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from isolume.app.options import (
    EXIT_INTERRUPTED,
    CLIError,
    add_volume_options,
    check_picture_memory,
    floats,
    isovalue,
    load_volume,
    parse_albedo,
    parse_lighting,
    parse_size,
)
from isolume.baking.config import DEFAULT_ALBEDO, DEFAULT_BOUNCES, DEFAULT_ENV

HELP = "path-trace a reference image of the isosurface (linear EXR + standard error)"
CHECKPOINT_SECONDS = 60.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume reference``."""
    add_volume_options(p, optional=False)
    p.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    p.add_argument("--out", required=True,
                   help="FILE.exr (also FILE.json and FILE.state.npz; resumed if present)")
    p.add_argument("--spp", type=int, default=64, help="samples (paths) per pixel (default 64)")
    p.add_argument("--size", default="512x512", help="WxH pixels (default 512x512)")
    p.add_argument("--view", default="30,30",
                   help="AZ,EL[,DIST]: azimuth and elevation (degrees) around the surface's "
                   "box, DIST in the box's diagonals (default 30,30 and as near as frames "
                   "the box)")
    p.add_argument("--env", default=DEFAULT_ENV,
                   help="constant:R,G,B | sky[:k=v,...] | FILE.exr/.hdr[@angular] | none "
                   f"(default {DEFAULT_ENV}, as render, view and bake)")
    p.add_argument("--env-rotation", default="0,0", help="AZ,EL degrees, as in render")
    p.add_argument("--light", action="append", metavar="SPEC",
                   help="point:X,Y,Z:R,G,B or dir:X,Y,Z:R,G,B (repeatable)")
    p.add_argument("--albedo", default=str(DEFAULT_ALBEDO),
                   help=f"A or R,G,B diffuse reflectance (default {DEFAULT_ALBEDO})")
    p.add_argument("--bounces", type=int, default=DEFAULT_BOUNCES,
                   help=f"diffuse bounces (0 = direct; default {DEFAULT_BOUNCES})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--workers", type=int, default=None, help="threads (default: all cores)")
    p.add_argument("--normals", default="smooth", choices=["smooth", "gradient"],
                   help="first-vertex normals: smoothed (default) or plain gradient")
    p.add_argument("--flip-normals", action="store_true", help="material less dense than air")


@dataclasses.dataclass(frozen=True)
class _Outputs:
    """The three files of one reference."""

    exr: Path
    sidecar: Path
    state: Path

    @classmethod
    def for_exr(cls, exr: Path) -> _Outputs:
        return cls(exr, exr.with_suffix(".json"), exr.with_suffix(".state.npz"))


def _check_numbers(args: argparse.Namespace) -> None:
    """Reject bad counts before any work is done."""
    if args.spp < 1:
        raise CLIError(f"--spp {args.spp}: expected at least 1 sample per pixel")


def _camera(args: argparse.Namespace, volume, iso: float):
    """(camera, (width, height)) from --view and --size, as ``isolume render`` makes them
    for the surface at `iso`."""
    from isolume.app.render.camera import parse_view
    from isolume.app.render.renderer import framed_camera

    try:
        view = parse_view(args.view)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    size = parse_size(args.size)
    check_picture_memory(size, "local")
    return framed_camera(volume, iso, view, size), size


def _config(args: argparse.Namespace):
    """The `BakeConfig` of the lighting and the integrator (samples = --spp, however
    many: a bake's cap on them applies to its noise target, which a reference has not)."""
    from isolume.baking.config import BakeConfig

    return BakeConfig.lit_by(
        parse_lighting(args.env, args.light),
        mode="irradiance", samples=args.spp, max_samples=max(args.spp, BakeConfig.max_samples),
        bounces=args.bounces,
        albedo=parse_albedo(args.albedo), seed=args.seed, flip_normals=args.flip_normals,
    )


def _env_rotation(text: str) -> np.ndarray | None:
    """(3, 3) rotation of ``--env-rotation AZ,EL``; None for the identity."""
    from isolume.baking.sh import rotation_from_az_el

    az, el = floats(text, 2, "--env-rotation")
    return None if az == el == 0 else rotation_from_az_el(az, el)


def _resume(outputs: _Outputs, tracer):
    """(stats, totals of earlier runs) from the state file, or fresh ones.

    Raises:
        BakeError: the state file holds a reference of another scene or camera.
    """
    from isolume.baking.errors import BakeError
    from isolume.baking.reference import PixelStats, load_state

    if not outputs.state.exists():
        return PixelStats.empty(tracer.pixels), {}
    stats, meta = load_state(outputs.state)
    if not tracer.holds(stats, meta):
        raise BakeError(
            f"{outputs.state}: holds a reference of another volume, camera or lighting; to "
            "add samples repeat its settings, or delete it (or choose another --out)")
    return stats, meta.get("totals", {})


def _totals(previous: dict, counters) -> dict:
    """Rays, paths and seconds of this run (`TraceCounters`) added to earlier runs'."""
    c = counters
    add = {"rays": c.primary_rays + c.rays, "path_rays": c.rays, "paths": c.paths,
           "seconds": c.setup_seconds + c.run_seconds, "trace_seconds": c.run_seconds,
           "embree_seconds": c.embree_seconds, "runs": 1}
    return {k: type(v)(previous.get(k, 0)) + v for k, v in add.items()}


def _camera_dict(camera, size: tuple[int, int]) -> dict:
    d = dataclasses.asdict(camera)
    d.update(size=list(size), eye=[float(v) for v in camera.eye])
    return d


def _summary(image, stats, hit_pixels: np.ndarray) -> dict:
    """spp reached and the standard error relative to the surface radiance."""
    if len(hit_pixels) == 0:
        return {"spp_min": 0, "spp_max": 0, "surface_pixels": 0, "relative_stderr": None}
    lum = np.array([0.2126, 0.7152, 0.0722])
    mean = image.radiance[hit_pixels] @ lum
    se = image.stderr[hit_pixels] @ lum
    counts = stats.count[hit_pixels]
    rel = float(np.sqrt(np.mean(se**2)) / max(float(np.mean(mean)), 1e-30))
    rel = rel if np.isfinite(rel) else None  # fewer than 2 samples: unknown
    return {"spp_min": int(counts.min()), "spp_max": int(counts.max()),
            "surface_pixels": len(hit_pixels), "relative_stderr": rel}


def _save(outputs: _Outputs, tracer, stats, meta: dict, size: tuple[int, int]) -> dict:
    """Write state, EXR and sidecar; returns the sidecar's dict."""
    from isolume.app.render.images import write_exr
    from isolume.baking.reference import save_state
    from isolume.volumes.writing import atomic_write

    save_state(outputs.state, stats, meta)
    w, h = size
    image = tracer.image(stats)
    extra = {"stderr": image.stderr.reshape(h, w, 3),
             "mask": image.mask.reshape(h, w).astype(np.float32)}
    atomic_write(outputs.exr, lambda p: write_exr(p, image.radiance.reshape(h, w, 3), extra))
    totals = meta["totals"]
    summary = _summary(image, stats, tracer.hits.pixels)
    sidecar = {
        "spp": meta["spp"], **summary, **totals,
        "rays_per_second": totals["path_rays"] / max(totals["trace_seconds"], 1e-9),
        "seconds_per_spp": totals["trace_seconds"] / max(summary["spp_max"], 1),
        "camera": meta["camera"], "config": tracer.config.to_dict(), "iso": tracer.iso,
        "volume": tracer.identity["volume"], "normals": tracer.identity["normals"],
        "env_rotation": meta["env_rotation"], "triangles": len(tracer.mesh.faces),
        "state": outputs.state.name,
    }
    atomic_write(outputs.sidecar,
                  lambda p: Path(p).write_text(json.dumps(sidecar, indent=2) + "\n"))
    return sidecar


@contextlib.contextmanager
def _graceful_interrupt():
    """A `threading.Event` set by the first Ctrl-C (the tracer then stops after the job it
    is committing, and the work done is saved); a second Ctrl-C interrupts at once."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop  # signal handlers can only be set in the main thread
        return

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def _progress(total: int):
    from tqdm import tqdm

    return tqdm(total=total, unit="path", unit_scale=True, dynamic_ncols=True,
                smoothing=0.1, desc="reference")


def run(args: argparse.Namespace) -> int:
    """Trace (or extend) the reference image; returns the exit status."""
    from isolume.app.render.images import check_output_path
    from isolume.baking.reference import ReferenceTracer

    outputs = _Outputs.for_exr(check_output_path(args.out, (".exr",)))
    _check_numbers(args)
    config = _config(args)
    rotation = _env_rotation(args.env_rotation)
    volume = load_volume(args)
    iso = isovalue(volume, args.iso)
    camera, size = _camera(args, volume, iso)
    origins, dirs = camera.primary_rays(*size)
    with ReferenceTracer(volume, iso, origins, dirs, config, smooth=args.normals == "smooth",
                         env_rotation=rotation, workers=args.workers) as tracer:
        if tracer.mesh.empty:
            print(f"isolume: warning: {tracer.mesh.message}", file=sys.stderr)
        stats, previous = _resume(outputs, tracer)
        meta = {"identity": tracer.identity, "spp": args.spp, "totals": previous,
                "camera": _camera_dict(camera, size), "env_rotation": args.env_rotation}
        done_before = stats.count.copy()
        last_save = [time.perf_counter()]

        def checkpoint() -> None:
            if time.perf_counter() - last_save[0] > CHECKPOINT_SECONDS:
                meta["totals"] = _totals(previous, tracer.counters)
                _save(outputs, tracer, stats, meta, size)
                last_save[0] = time.perf_counter()

        bar = _progress(tracer.pending_paths(stats, args.spp))
        with _graceful_interrupt() as stop:
            complete = tracer.run(stats, args.spp, bar=bar, after_pass=checkpoint, stop=stop)
        bar.close()
        meta["totals"] = _totals(previous, tracer.counters)
        sidecar = _save(outputs, tracer, stats, meta, size)
        if not complete:
            print(f"isolume: interrupted; {sidecar['spp_min']} to {sidecar['spp_max']} samples "
                  f"per pixel saved in {outputs.state}; run the same command again to resume",
                  file=sys.stderr)
            return EXIT_INTERRUPTED
        added = int((stats.count - done_before).max(initial=0))
    _report(outputs, sidecar, volume, iso, size, tracer.counters, added)
    return 0


def _report(outputs: _Outputs, sidecar: dict, volume, iso: float, size, counters,
            added_spp: int) -> None:
    """One line on what was written and how fast this run was."""
    rel = sidecar["relative_stderr"]
    error = "unknown" if rel is None else f"{rel:.2%}"
    speed = (f"setup {counters.setup_seconds:.1f} s, {counters.rays:,} rays in "
             f"{counters.run_seconds:.1f} s ({counters.rays_per_second / 1e6:.2f} Mrays/s")
    if added_spp:
        speed += f", {counters.run_seconds / added_spp:.3g} s/spp"
    speed += ")"
    print(f"wrote {outputs.exr} ({size[0]}x{size[1]}, {volume.name} at iso {iso:.6g}, "
          f"{sidecar['surface_pixels']:,} surface pixels, {sidecar['spp_min']} spp, "
          f"relative standard error {error}; {speed})")
