"""``isolume bench``: benchmarks that print figures (never timed assertions).

* ``bench bake``: the baker's rays per second against bare embreex on the same meshes and
  rays, measured in the same run: a plain bake is timed, then the same bake (the same
  rays: bakes are deterministic) runs again with the rays it traces on each level scene
  recorded and, as soon as the level is done, traced again on that scene straight
  through embreex with the same number of threads (the timed bake copies no ray). Two
  ratios: the tracing loop's (level scenes excluded), and end to end (every
  ray over the whole bake's wall time: planning, level scenes and tracing). Also the
  full-bake figures (time, active texels, levels, rays, the level scenes' cost split
  into marching cubes and Embree).
* ``bench frames`` and ``bench lazy``: `app.bench.view`; ``bench accuracy``: the default
  render's and a default bake's lighting against path tracing on every scan
  (`app.bench.accuracy`); ``bench scale``: peak memory and time against the volume's size
  (`app.bench.scale`); ``bench cores``: parallel efficiency per stage against threads, and
  the speed-up predicted at 16 and 64 threads (`app.bench.cores`); ``bench front``: the
  bake's error against paths, time and bytes over several accuracy sweeps
  (`app.bench.front`).
"""

from __future__ import annotations

import argparse
import json
import time

from isolume.app.options import description_of
from isolume.baking.config import DEFAULT_BOUNCES
from isolume.volumes import cores

HELP = ("benchmarks: baker throughput against bare embreex, frame times, lazy GI, lighting "
        "accuracy, memory and time against size")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", required=True)
    p = sub.add_parser("bake", help="baker rays/s against bare embreex, full-bake figures",
                       description="The baker's rays per second against bare embreex on "
                       "the same rays, and the figures of a whole bake.")
    p.add_argument("volume", nargs="?", default="synthetic:engine",
                   help="volume (default synthetic:engine)")
    p.add_argument("--samples", type=int, default=32, help="paths per texel (default 32)")
    p.add_argument("--bounces", type=int, default=DEFAULT_BOUNCES,
                   help=f"bounces per path (default {DEFAULT_BOUNCES})")
    p.add_argument("--env", default="constant:1,1,1",
                   help="environment light (default constant:1,1,1)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="lattice texels per voxel along the finest axis")
    p.add_argument("--iso-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="isovalues to bake (default: around the suggested ones)")
    p.add_argument("--workers", type=int, default=None,
                   help="tracing threads (default: all cores)")
    p.add_argument("--json", help="also write the figures to this JSON file")
    for name, module in _VIEW_BENCHES.items():
        bench = _view_module()
        if bench is not None and hasattr(bench, f"add_{name}_arguments"):
            getattr(bench, f"add_{name}_arguments")(
                sub.add_parser(name, help=module, description=description_of(module)))
    accuracy = _accuracy_module()
    accuracy.add_arguments(sub.add_parser("accuracy", help=accuracy.HELP,
                                          description=description_of(accuracy.HELP)))
    from isolume.app.bench import scale

    scale.add_arguments(sub.add_parser("scale", help=scale.HELP,
                                       description=description_of(scale.HELP)))
    from isolume.app.bench import front

    front.add_arguments(sub.add_parser("front", help=front.HELP,
                                       description=description_of(front.HELP)))
    from isolume.app.bench import cores as cores_bench

    cores_bench.add_arguments(sub.add_parser("cores", help=cores_bench.HELP,
                                             description=description_of(cores_bench.HELP)))


_VIEW_BENCHES = {"frames": "frame time per shading mode (llvmpipe, EGL)",
                 "lazy": "lazy GI: time to a first estimate and to a picture within 5 %%"}


def _view_module():
    from isolume.app.bench import view

    return view


def _accuracy_module():
    from isolume.app.bench import accuracy

    return accuracy


def run(args: argparse.Namespace) -> int:
    if args.bench == "bake":
        return bench_bake(args)
    if args.bench == "accuracy":
        return _accuracy_module().run(args)
    if args.bench == "front":
        from isolume.app.bench import front

        return front.run(args)
    if args.bench == "scale":
        from isolume.app.bench import scale

        return scale.run(args)
    if args.bench == "cores":
        from isolume.app.bench import cores as cores_bench

        return cores_bench.run(args)
    return getattr(_view_module(), args.bench)(args)


def bench_bake(args: argparse.Namespace) -> int:
    """Bake twice with the same settings (a bake traces the same rays every time): once
    plain, timed end to end; once with every ray recorded and replayed on bare embreex
    after each level. Print the plain bake's rates against the bare one."""

    import numpy as np

    from isolume import volumes
    from isolume.baking.bake import Baker
    from isolume.baking.config import BakeConfig
    from isolume.baking.lighting import lighting_of

    vol = volumes.load(args.volume)
    config = BakeConfig.lit_by(lighting_of(args.env), samples=args.samples,
                               bounces=args.bounces, scale=args.scale,
                               iso_range=tuple(args.iso_range) if args.iso_range else None)
    workers = args.workers or cores.threads()
    began = time.perf_counter()
    baker = Baker(vol, config, workers=workers)
    plan_seconds = time.perf_counter() - began
    start = time.perf_counter()
    baker.run()
    wall = time.perf_counter() - start
    baker.close()
    bare = _bare_rate(volumes.load(args.volume), config, workers)
    figures = _bake_figures(vol, args, workers, baker, wall, plan_seconds, bare)
    _print_bake_figures(figures)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=1)
    np.seterr(all="warn")
    return 0


def _bare_rate(vol, config, workers: int) -> dict:
    """The bake of `config` again, every ray it traces on a level scene recorded (each
    level's apart) and, as soon as no chunk of that level is running, traced again on its
    scene straight through embreex on `workers` threads. Recording costs the baker time
    and memory (28 bytes a ray), so this bake is not the one timed.

    Returns:
        rays and seconds of the replays ("rays", "seconds").
    """
    from collections import Counter
    from concurrent.futures import ThreadPoolExecutor

    from isolume.baking.bake import Baker
    from isolume.baking.trace import RayRecorder, replay

    baker = Baker(vol, config, workers=workers)
    bare = {"rays": 0, "seconds": 0.0}
    backend = baker.backend
    original_scene, original_submit, original_collect = (
        backend._scene, backend._submit_level, backend._collect)
    recorded: dict[int, tuple[object, RayRecorder]] = {}  # level -> (scene, its recorder)
    running: Counter[int] = Counter()  # chunks queued and not yet collected, per level

    def recording_scene(level):
        scene = original_scene(level)
        if not scene.empty:
            scene.recorder = recorded.setdefault(level, (scene, RayRecorder()))[1]
        return scene

    def counted_submit(lay, sums, batch):
        chunks = original_submit(lay, sums, batch)
        running[lay.step.level] += len(chunks)
        return chunks

    def collect_then_replay(chunks, level, report):
        original_collect(chunks, level, report)
        running[level] -= len(chunks)
        if running[level] == 0 and level in recorded:  # none of its rays still coming
            scene, recorder = recorded[level]
            batches = recorder.batches()
            if batches:
                rays, seconds = replay(scene, batches, pool)
                bare["rays"] += rays
                bare["seconds"] += seconds
            recorder.clear()

    backend._scene, backend._submit_level, backend._collect = (
        recording_scene, counted_submit, collect_then_replay)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        baker.run()
    baker.close()
    return bare


def _bake_figures(vol, args, workers: int, baker, wall: float, plan_seconds: float,
                  bare: dict) -> dict:
    """The figures of one `bench_bake` run (JSON-ready). `wall`: the plain bake's `run`
    seconds; `plan_seconds`: making its `Baker` (plan, kernels)."""
    stats = baker.stats
    assert stats.rays == bare["rays"], "the replayed bake must trace exactly the timed one's rays"
    plan = baker.lattice.meta["plan"]
    tracing_wall = wall - stats.scene_seconds  # the baker's own loop, scenes excluded
    bare_rate = bare["rays"] / bare["seconds"]
    end_to_end = plan_seconds + wall
    return {
        "volume": vol.source or vol.name, "shape": list(vol.data.shape),
        "samples": args.samples, "bounces": args.bounces, "scale": args.scale,
        "env": args.env, "iso_range": plan["iso_range"], "workers": workers,
        "active_texels": plan["active_texels"], "total_texels": plan["total_texels"],
        "levels": len(plan["levels"]), "move_limit_voxels": plan["move_limit_voxels"],
        "rays": stats.rays, "plan_seconds": plan_seconds, "bake_seconds": wall,
        "end_to_end_seconds": end_to_end, "scene_seconds": stats.scene_seconds,
        "scenes": stats.scenes, "marching_cubes_seconds": stats.mesh_seconds,
        "embree_build_seconds": stats.embree_seconds,
        "baker_rays_per_s": stats.rays / tracing_wall, "bare_embreex_rays_per_s": bare_rate,
        "ratio": stats.rays / tracing_wall / bare_rate,
        "chunk_ratio": stats.rays / stats.trace_seconds * workers / bare_rate,
        "end_to_end_ratio": stats.rays / end_to_end / bare_rate,
        "texels_per_s": plan["active_texels"] / end_to_end,
    }


def _print_bake_figures(f: dict) -> None:
    shape = " x ".join(str(n) for n in f["shape"][::-1])
    lo, hi = f["iso_range"]
    print(f"volume {f['volume']} ({shape}), {f['samples']} paths/texel, {f['bounces']} "
          f"bounces, scale {f['scale']:g}, iso range [{lo:g}, {hi:g}], {f['workers']} workers")
    print(f"active texels {f['active_texels']:,} of {f['total_texels']:,} "
          f"({f['active_texels'] / f['total_texels']:.1%}), {f['levels']} levels "
          f"(move limit {f['move_limit_voxels']:.2g} voxels)")
    per = max(f["scenes"], 1)
    print(f"end to end {f['end_to_end_seconds']:.1f} s: plan {f['plan_seconds']:.1f} s, level "
          f"scenes {f['scene_seconds']:.1f} s ({f['scenes']} scenes: marching cubes "
          f"{f['marching_cubes_seconds'] / per:.2f} s + Embree "
          f"{f['embree_build_seconds'] / per:.2f} s each), tracing "
          f"{f['bake_seconds'] - f['scene_seconds']:.1f} s; {f['rays']:,} rays")
    print(f"baker       {f['baker_rays_per_s'] / 1e6:.3f} Mrays/s (tracing loop, scenes "
          "excluded)")
    print(f"bare embree {f['bare_embreex_rays_per_s'] / 1e6:.3f} Mrays/s (same meshes and rays, "
          f"{f['workers']} threads)")
    print(f"ratio       {f['ratio']:.2f} tracing loop (goal >= 0.8), "
          f"{f['end_to_end_ratio']:.2f} end to end (rays over the whole bake's wall time); "
          f"{f['chunk_ratio']:.2f} inside the compiled chunks (Embree and the path arithmetic "
          "per thread, without the loop's waits and lay-out)")
