"""The only module that imports embreex: triangle scenes and batched ray queries.

embreex releases the GIL inside `run`, so worker threads trace concurrently.
"""

from __future__ import annotations

import time

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

_MISS = -1


class RayStats:
    """Counts rays and seconds spent inside Embree (thread-safe enough: += on ints)."""

    def __init__(self) -> None:
        self.rays = 0
        self.seconds = 0.0

    def add(self, rays: int, seconds: float) -> None:
        self.rays += rays
        self.seconds += seconds


class Scene:
    """One triangle mesh in an Embree scene.

    Args:
        vertices: (V, 3) world positions.
        faces: (F, 3) vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.empty = len(faces) == 0
        self.faces = np.asarray(faces, np.int32)
        self.vertices = np.ascontiguousarray(vertices, np.float32)
        self.recorder: list | None = None  # benchmarks: (query, origins, dirs, tfar) per call
        if not self.empty:
            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(self._scene, self.vertices, np.ascontiguousarray(self.faces))
            _build_bvh(self._scene)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, stats: RayStats | None = None
                  ) -> dict[str, np.ndarray]:
        """Closest hits of (N, 3) rays.

        Returns:
            dict with ``hit`` (N,) bool, ``t`` (N,) distance, ``prim`` (N,) triangle id,
            ``u``, ``v`` (N,) barycentrics, ``ng`` (N, 3) unnormalised geometric normal.
        """
        n = len(origins)
        if self.empty or n == 0:
            return {"hit": np.zeros(n, bool), "t": np.full(n, np.inf),
                    "prim": np.full(n, _MISS), "u": np.zeros(n), "v": np.zeros(n),
                    "ng": np.zeros((n, 3))}
        origins = np.ascontiguousarray(origins, np.float32)
        dirs = np.ascontiguousarray(dirs, np.float32)
        if self.recorder is not None:
            self.recorder.append(("INTERSECT", origins, dirs, None))
        start = time.perf_counter()
        out = self._scene.run(origins, dirs, output=1)
        if stats is not None:
            stats.add(n, time.perf_counter() - start)
        prim = out["primID"]
        return {"hit": prim != _MISS, "t": out["tfar"], "prim": prim, "u": out["u"],
                "v": out["v"], "ng": out["Ng"]}

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None,
                 stats: RayStats | None = None) -> np.ndarray:
        """(N,) bool: is anything hit before distance `tfar` (default: infinity)?"""
        n = len(origins)
        if self.empty or n == 0:
            return np.zeros(n, bool)
        dists = None
        if tfar is not None:
            dists = np.ascontiguousarray(np.minimum(tfar, 1e30), np.float32)
        origins = np.ascontiguousarray(origins, np.float32)
        dirs = np.ascontiguousarray(dirs, np.float32)
        if self.recorder is not None:
            self.recorder.append(("OCCLUDED", origins, dirs, dists))
        start = time.perf_counter()
        out = self._scene.run(origins, dirs, dists=dists, query="OCCLUDED")
        if stats is not None:
            stats.add(n, time.perf_counter() - start)
        return out != _MISS


def _build_bvh(scene) -> None:
    """Commit `scene` now (embreex builds the BVH on the first query): the build is part of
    making the scene, not of tracing."""
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))


def replay(scene: Scene, batches: list, pool) -> tuple[int, float]:
    """Trace recorded ray batches again on `scene`'s Embree scene, straight through
    embreex (the same query kinds, on the threads of `pool`, a ThreadPoolExecutor) and
    time it: the baseline the baker's throughput is compared with.

    Returns:
        (rays, seconds of wall time for the tracing alone).
    """
    embree = scene._scene

    def trace(batch) -> int:
        query, origins, dirs, dists = batch
        if query == "INTERSECT":
            embree.run(origins, dirs, output=1)
        else:
            embree.run(origins, dirs, dists=dists, query="OCCLUDED")
        return len(origins)

    start = time.perf_counter()
    rays = sum(pool.map(trace, batches))
    return rays, time.perf_counter() - start
