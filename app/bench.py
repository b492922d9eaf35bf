"""``isolume bench``: benchmarks that print figures (never timed assertions).

* ``bench bake``: the baker's rays per second against bare embreex on the same meshes and
  rays, measured in the same run: the rays the baker traces on each level scene are
  recorded and, as soon as the level is done, traced again on that scene straight through
  embreex with the same number of threads — interleaved level by level, so that both
  rates see the same load on a shared machine. Also the full-bake figures (time, active
  texels, levels, rays).
"""

from __future__ import annotations

import argparse
import json
import time

HELP = "benchmarks: baker throughput against bare embreex, frame times, lazy GI"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", required=True)
    p = sub.add_parser("bake", help="baker rays/s against bare embreex, full-bake figures")
    p.add_argument("volume", nargs="?", default="synthetic:engine",
                   help="volume (default synthetic:engine)")
    p.add_argument("--samples", type=int, default=32)
    p.add_argument("--bounces", type=int, default=2)
    p.add_argument("--env", default="constant:1,1,1")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--json", help="also write the figures to this JSON file")
    for name, module in _VIEW_BENCHES.items():
        bench = _view_module()
        if bench is not None and hasattr(bench, f"add_{name}_arguments"):
            getattr(bench, f"add_{name}_arguments")(sub.add_parser(name, help=module))


_VIEW_BENCHES = {"frames": "frame time per shading mode (llvmpipe, EGL)",
                 "lazy": "lazy GI: time to a first estimate and to a picture within 5 %"}


def _view_module():
    import importlib.util

    if importlib.util.find_spec("app.bench_view") is None:
        return None
    import app.bench_view

    return app.bench_view


def run(args: argparse.Namespace) -> int:
    if args.bench == "bake":
        return bench_bake(args)
    return getattr(_view_module(), args.bench)(args)


def bench_bake(args: argparse.Namespace) -> int:
    """Bake with every ray recorded and replayed on bare embreex after each level; print
    both rates."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    import volumes
    from baking.bake import Baker
    from baking.config import BakeConfig
    from baking.trace import RayRecorder, replay

    vol = volumes.load(args.volume)
    config = BakeConfig(samples=args.samples, bounces=args.bounces, env=args.env)
    workers = args.workers or os.cpu_count() or 1
    baker = Baker(vol, config, workers=workers)
    bare = {"rays": 0, "seconds": 0.0, "wall": 0.0}
    original_scene, original_collect = baker._scene, baker._collect
    recorder = RayRecorder()

    def recording_scene(level):
        scene = original_scene(level)
        if not scene.empty:
            scene.recorder = recorder
        return scene

    def collect_then_replay(jobs, level, bar):
        original_collect(jobs, level, bar)
        start = time.perf_counter()
        scene = baker._scenes.get(level)
        batches = recorder.batches()
        if scene is not None and batches:
            rays, seconds = replay(scene, batches, pool)
            bare["rays"] += rays
            bare["seconds"] += seconds
        recorder.clear()
        bare["wall"] += time.perf_counter() - start

    baker._scene, baker._collect = recording_scene, collect_then_replay
    with ThreadPoolExecutor(max_workers=workers) as pool:
        start = time.perf_counter()
        baker.run()
        wall = time.perf_counter() - start - bare["wall"]
    baker.close()
    stats = baker.stats
    tracing_wall = wall - stats.scene_seconds  # the baker's own loop, scenes excluded
    bare_rays, bare_seconds = bare["rays"], bare["seconds"]
    baker_rate = stats.rays / tracing_wall
    bare_rate = bare_rays / bare_seconds
    plan = baker.lattice.meta["plan"]
    figures = {
        "volume": vol.source or vol.name, "shape": list(vol.data.shape),
        "samples": args.samples, "bounces": args.bounces, "workers": workers,
        "active_texels": plan["active_texels"], "total_texels": plan["total_texels"],
        "levels": len(plan["levels"]), "rays": stats.rays, "bake_seconds": wall,
        "scene_seconds": stats.scene_seconds, "baker_rays_per_s": baker_rate,
        "bare_embreex_rays_per_s": bare_rate, "ratio": baker_rate / bare_rate,
        "texels_per_s": plan["active_texels"] / wall,
    }
    assert stats.rays == bare_rays, "replay must trace exactly the baker's rays"
    print(f"volume {figures['volume']} {vol.data.shape[::-1]} (x,y,z), {args.samples} paths/texel, "
          f"{args.bounces} bounces, {workers} workers")
    print(f"active texels {plan['active_texels']:,} of {plan['total_texels']:,} "
          f"({plan['active_texels'] / plan['total_texels']:.1%}), {len(plan['levels'])} levels")
    print(f"bake {wall:.1f} s ({stats.scene_seconds:.1f} s building level scenes), "
          f"{stats.rays:,} rays")
    print(f"baker       {baker_rate / 1e6:.3f} Mrays/s (tracing loop, scenes excluded)")
    print(f"bare embree {bare_rate / 1e6:.3f} Mrays/s (same meshes and rays, {workers} threads)")
    print(f"ratio       {figures['ratio']:.2f} (goal >= 0.8)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=1)
    np.seterr(all="warn")
    return 0
