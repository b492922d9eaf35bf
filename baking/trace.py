"""The only module that imports embreex: triangle scenes and batched ray queries.

embreex releases the GIL inside `run`, so worker threads trace concurrently.
"""

from __future__ import annotations

import gc
import threading
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


class RayRecorder:
    """Benchmarks: a copy of every ray batch a scene traces, to trace again on bare embreex.

    Copies go into buffers of each tracing thread that are reused from level to level
    (`clear`): holding on to the tracer's own arrays instead would keep the allocator from
    reusing their memory, and the tracer would pay page faults on fresh memory that a
    real bake never pays.
    """

    def __init__(self) -> None:
        self._local = threading.local()
        self._buffers: list[_RecordBuffer] = []
        self._lock = threading.Lock()

    def add(self, query: str, origins: np.ndarray, dirs: np.ndarray,
            dists: np.ndarray | None) -> None:
        """Copy one batch: (N, 3) float32 origins and directions, (N,) distances or None."""
        buffer = getattr(self._local, "buffer", None)
        if buffer is None:
            buffer = self._local.buffer = _RecordBuffer()
            with self._lock:
                self._buffers.append(buffer)
        buffer.add(query, origins, dirs, dists)

    def batches(self) -> list[tuple]:
        """Every batch recorded since `clear`: (query, origins, dirs, dists or None)."""
        return [batch for buffer in self._buffers for batch in buffer.batches()]

    def clear(self) -> None:
        """Forget the batches; keep the buffers."""
        for buffer in self._buffers:
            buffer.used, buffer.spans = 0, []


class _RecordBuffer:
    """One thread's recorded rays, one row per axis as the path tracer holds them:
    growing (7, capacity) float32 rows of origin, direction and distance, and the (query,
    start, stop, has distances) of each batch."""

    def __init__(self) -> None:
        self.rows = np.empty((7, 0), np.float32)
        self.used = 0
        self.spans: list[tuple[str, int, int, bool]] = []

    def add(self, query: str, origins, dirs, dists) -> None:
        n = len(origins)
        if self.used + n > self.rows.shape[1]:
            grown = np.empty((7, max(2 * self.rows.shape[1], self.used + n)), np.float32)
            grown[:, :self.used] = self.rows[:, :self.used]
            self.rows = grown
        rows = self.rows[:, self.used:self.used + n]
        rows[0:3], rows[3:6] = origins.T, dirs.T
        if dists is not None:
            rows[6] = dists
        self.spans.append((query, self.used, self.used + n, dists is not None))
        self.used += n

    def batches(self) -> list[tuple]:
        return [(query, self.rows[0:3, lo:hi].T, self.rows[3:6, lo:hi].T,
                 self.rows[6, lo:hi] if has_dists else None)
                for query, lo, hi, has_dists in self.spans]


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
        self.recorder: RayRecorder | None = None  # benchmarks: a copy of every batch
        if not self.empty:
            self._scene = rtcore_scene.EmbreeScene()
            _attach_mesh(self._scene, self.vertices, self.faces)
            _build_bvh(self._scene)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, stats: RayStats | None = None
                  ) -> dict[str, np.ndarray]:
        """Closest hits of (N, 3) rays (float32 arrays of any strides are used as they are).

        Returns:
            dict with ``t`` (N,) distance, ``prim`` (N,) triangle id (< 0: no hit),
            ``u``, ``v`` (N,) barycentrics, ``ng`` (N, 3) unnormalised geometric normal.
        """
        n = len(origins)
        if self.empty or n == 0:
            return {"t": np.full(n, np.inf, np.float32), "prim": np.full(n, _MISS, np.int32),
                    "u": np.zeros(n, np.float32), "v": np.zeros(n, np.float32),
                    "ng": np.zeros((n, 3), np.float32)}
        origins = np.asarray(origins, np.float32)
        dirs = np.asarray(dirs, np.float32)
        if self.recorder is not None:
            self.recorder.add("INTERSECT", origins, dirs, None)
        start = time.perf_counter()
        out = self._scene.run(origins, dirs, output=1)
        if stats is not None:
            stats.add(n, time.perf_counter() - start)
        return {"t": out["tfar"], "prim": out["primID"], "u": out["u"], "v": out["v"],
                "ng": out["Ng"]}

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None,
                 stats: RayStats | None = None) -> np.ndarray:
        """(N,) bool: is anything hit before distance `tfar` (default: infinity)? (Rays
        as in `intersect`.)"""
        n = len(origins)
        if self.empty or n == 0:
            return np.zeros(n, bool)
        dists = None
        if tfar is not None:
            dists = np.ascontiguousarray(np.minimum(tfar, 1e30), np.float32)
        origins = np.asarray(origins, np.float32)
        dirs = np.asarray(dirs, np.float32)
        if self.recorder is not None:
            self.recorder.add("OCCLUDED", origins, dirs, dists)
        start = time.perf_counter()
        out = self._scene.run(origins, dirs, dists=dists, query="OCCLUDED")
        if stats is not None:
            stats.add(n, time.perf_counter() - start)
        return out != _MISS


def _attach_mesh(scene, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Give embreex the (V, 3) float32 vertices and (F, 3) int32 faces of a mesh.

    embreex copies them into Embree's buffers element by element with generic Python
    indexing (``vertices[i, k]``, ``faces[i][k]``): from numpy arrays every element first
    becomes a numpy scalar, and a row a view — 0.9 s for a 580 k-triangle level of the
    engine CT, most of a level scene's cost. From an object array of Python floats and an
    array of one list of ints per triangle it reads the same values three times faster
    (0.3 s, plus 0.15 s to make them, the garbage collector paused meanwhile: it would
    otherwise scan the half million new lists again and again). An embreex that refuses
    such arrays (typed buffers) gets the numpy arrays.
    """
    collecting = gc.isenabled()
    gc.disable()
    try:
        rows = np.fromiter(faces.tolist(), dtype=object, count=len(faces))
        points = vertices.astype(object)
    finally:
        if collecting:
            gc.enable()
    try:
        TriangleMesh(scene, points, rows)
    except (TypeError, ValueError):
        TriangleMesh(scene, vertices, np.ascontiguousarray(faces))


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
