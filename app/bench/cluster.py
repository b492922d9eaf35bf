"""Cluster bake figures and the scaling model: ``python -m isolume.app.bench.cluster [VOLUME]``.

Bakes the same lattice four ways in one run — 1 and 2 threads (`bake.Baker`), 1 and 2
worker processes of a local Dask cluster (a `bake.Baker` with a `cluster.ClusterBackend`;
the cluster started and its workers warmed by a tiny bake beforehand, as a running one
would be) — checks that the four lattices are the same bits, and prints wall and CPU
seconds (this process and the workers: steadier than wall times on a shared machine) and
the model's inputs: the level count K, the seconds per level scene S (as a worker builds
it: marching cubes and BVH), the seconds per path c (one thread), the master's serial
seconds M (the plan), a worker's set-up U and the job's size J — S, c and M in CPU
seconds (what an unloaded core would take). The model for W single-threaded workers
(`predict`):

    T(W) = M + U + S · max(K / W, 1) + P · c / W + J · W / bandwidth

While W ≤ K each level's tasks go to one worker, so the K scenes are built about once in
all; past K workers the idle ones steal tasks and build the scenes of the levels they
steal from: at least one scene each. It stops scaling where P · c / W falls to M + U + S.
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from dataclasses import replace

import numpy as np

from isolume import volumes
from isolume.baking.bake import Baker
from isolume.baking.cluster import ClusterBackend, local_cluster
from isolume.baking.config import BakeConfig
from isolume.baking.passes import level_scene

WORKER_COUNTS = (1, 4, 16, 64)


def predict(workers: int, master_s: float, setup_s: float, scene_s: float, levels: int,
            paths: float, path_s: float, job_bytes: float = 0.0,
            bandwidth: float = 1.25e9) -> float:
    """Modelled bake seconds on `workers` single-threaded workers.

    Args:
        master_s: the master's serial seconds (the plan); setup_s: a worker's own set-up
            for the bake (kernels loaded), in parallel on all;
        scene_s: seconds per level scene; levels: K; paths: P; path_s: seconds per path
            on one thread;
        job_bytes: the scattered job, sent from the scheduler's machine to every worker
            at `bandwidth` bytes/s (10 Gbit/s by default).
    """
    return (master_s + setup_s + scene_s * max(levels / workers, 1.0)
            + paths * path_s / workers + job_bytes * workers / bandwidth)


def cpu_seconds() -> float:
    """CPU seconds (user + system) this process has used, all its threads."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _time_local(volume, config: BakeConfig, threads: int) -> tuple[float, float, Baker]:
    """(wall seconds, CPU seconds, baker) of a bake on `threads` threads."""
    t0, c0 = time.perf_counter(), cpu_seconds()
    baker = Baker(volume, config, workers=threads)
    baker.run()
    baker.close()
    return time.perf_counter() - t0, cpu_seconds() - c0, baker


def _time_cluster(volume, config: BakeConfig, client) -> tuple[float, float, Baker]:
    """(wall seconds, CPU seconds of this process and the workers, baker); the master's
    share of the CPU seconds is kept as ``baker.master_cpu``."""
    before = sum(client.run(cpu_seconds).values())
    t0, c0 = time.perf_counter(), cpu_seconds()
    baker = Baker(volume, config, backend=ClusterBackend(client=client))
    baker.run()
    baker.close()
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    baker.master_cpu = cpu
    return wall, cpu + sum(client.run(cpu_seconds).values()) - before, baker


def _row(name: str, wall: float, cpu: float, baker: Baker, base: float) -> None:
    s = baker.stats
    print(f"{name:>20}: {wall:7.1f} s  ({base / wall:4.2f}x 1 thread)  CPU {cpu:7.1f} s  "
          f"scenes {s.scene_seconds:6.1f} s  tracing {s.trace_seconds:7.1f} s  "
          f"{s.paths:,} paths  load {os.getloadavg()[0]:.1f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m isolume.app.bench.cluster",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("volume", nargs="?", default="synthetic:engine")
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--env", default="sky:sun=3")
    parser.add_argument("--target-voxels", type=float, default=512.0**3,
                        help="voxel count of the extrapolated volume (default 512³)")
    args = parser.parse_args(argv)
    from distributed import Client

    volume = volumes.load(args.volume)
    config = BakeConfig(samples=args.samples, bounces=args.bounces, env=args.env)
    c0 = cpu_seconds()
    plan_only = Baker(volume, config, workers=1)
    master_s = cpu_seconds() - c0
    plan_only.close()
    c0 = cpu_seconds()  # again, as the bakes below plan: with the volume's caches warm
    Baker(volume, config, workers=1).close()
    warm_plan_s = cpu_seconds() - c0
    scene_s = _scene_cpu_seconds(volume, config, plan_only.plan.levels)
    levels, active = len(plan_only.plan.levels), len(plan_only.plan.ids)
    print(f"{volume.name} {volume.data.shape[::-1]}: {active:,} active texels, {levels} levels, "
          f"plan {master_s:.1f} CPU s; {args.samples} paths/texel, {args.bounces} bounces, "
          f"{args.env}")
    # both clusters start (and load isolume's code) first, with this process's code:
    # a source edited later would make their code differ, and the workers refuse then
    with local_cluster(1) as small, Client(small) as one_client, \
            local_cluster(2) as pair, Client(pair) as two_client:
        for client in (one_client, two_client):
            _time_cluster(volumes.load("synthetic:sphere:16"), BakeConfig(samples=1), client)
        wall1, cpu1, one = _time_local(volume, config, 1)
        _row("1 thread", wall1, cpu1, one, wall1)
        wall, cpu, two = _time_local(volume, config, 2)
        _row("2 threads", wall, cpu, two, wall1)
        lattices = [one.lattice, two.lattice]
        for count, client in ((1, one_client), (2, two_client)):
            wall, cpu, baker = _time_cluster(volume, config, client)  # workers warm
            _row(f"{count} worker process" + "es" * (count > 1), wall, cpu, baker, wall1)
            print(f"{'':>22}CPU on this machine (plan, client) {baker.master_cpu:.1f} s, "
                  f"on the workers {cpu - baker.master_cpu:.1f} s")
            lattices.append(baker.lattice)
            moved = baker.backend.traffic
    same = all(np.array_equal(a.values, lattices[0].values) and
               np.array_equal(a.samples, lattices[0].samples) for a in lattices[1:])
    print(f"lattices identical to the bit: {same}")
    per_task = (moved.bytes_sent + moved.bytes_returned) / max(moved.tasks, 1)
    print(f"cluster traffic (2 workers): {moved.tasks} tasks, {per_task / 1e3:.1f} kB per task "
          f"({moved.bytes_sent / 1e6:.2f} MB sent, {moved.bytes_returned / 1e6:.2f} MB back), "
          f"job {moved.job_bytes / 1e6:.1f} MB per worker once, {moved.scene_builds} scene "
          f"builds for {levels} levels")
    # CPU seconds: what an unloaded core takes (wall times swell on a shared machine)
    path_s = (cpu1 - warm_plan_s - levels * scene_s) / max(one.stats.paths, 1)
    setup_s = _setup_seconds(volume)
    print(f"model inputs: K = {levels} levels, S = {scene_s:.3f} s per level scene, "
          f"c = {path_s * 1e6:.2f} µs per path (1 thread), M = {master_s:.1f} s plan, "
          f"U = {setup_s:.1f} s worker set-up, J = {moved.job_bytes / 1e6:.1f} MB job")
    _print_model(volume, config, master_s, setup_s, scene_s, path_s, active, moved.job_bytes,
                 args.target_voxels)
    return 0


def _scene_cpu_seconds(volume, config: BakeConfig, levels: np.ndarray, count: int = 3) -> float:
    """CPU seconds (Embree's threads included) per level scene: marching cubes and BVH of
    `count` levels spread over the plan's."""
    picked = levels[np.linspace(0, len(levels) - 1, min(count, len(levels))).astype(int)]
    c0 = cpu_seconds()
    for iso in picked:
        level_scene(volume, float(iso), config)
    return (cpu_seconds() - c0) / len(picked)


def _setup_seconds(volume) -> float:
    """A worker's set-up for a bake: its kernels loaded (cold process, numba's cache) and
    its first normals (`volumes.normals_at`: the gradient kernels loaded)."""
    import subprocess
    import sys

    code = "import time; t = time.perf_counter(); from isolume.baking import kernels; " \
           "kernels.warm_up(); print(time.perf_counter() - t)"
    warm = float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                check=True).stdout)
    fresh = volumes.Volume(volume.data, volume.spacing, volume.origin)
    t0 = time.perf_counter()
    volumes.normals_at(fresh, np.zeros((1, 3)))
    return warm + time.perf_counter() - t0


def _print_model(volume, config: BakeConfig, master_s: float, setup_s: float, scene_s: float,
                 path_s: float, active: int, job_bytes: int, target_voxels: float) -> None:
    """Modelled bake times at 100 paths per texel of this volume and of one of
    `target_voxels` voxels: active texels, the plan, the set-up, the job and the level
    scenes (marching cubes scans every voxel) grow with the voxel count; a path costs
    what it costs here; K is what the plan picks at 100 paths."""
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.plan import make_plan

    config = replace(config, samples=100)
    levels = len(make_plan(volume, LatticeGeometry.for_volume(volume, 1.0), config).levels)
    grow = target_voxels / volume.data.size
    print(f"modelled bake seconds at 100 paths/texel (K = {levels} levels; W single-threaded "
          "workers; job sent at 10 Gbit/s):")
    print(f"{'':>24}" + "".join(f"{f'W={w}':>8}" for w in WORKER_COUNTS) + "   floor")
    for name, g in ((volume.name, 1.0), (f"{target_voxels:.3g} voxels", grow)):
        inputs = (master_s * g, setup_s * g, scene_s * g, levels, active * g * 100, path_s)
        times = [predict(w, *inputs, job_bytes * g) for w in WORKER_COUNTS]
        floor = inputs[0] + inputs[1] + inputs[2]
        print(f"{name:>24}" + "".join(f"{t:8.0f}" for t in times) + f"{floor:8.0f}"
              f"   (1 worker / floor = {times[0] / floor:.0f}x)")


if __name__ == "__main__":
    raise SystemExit(main())
