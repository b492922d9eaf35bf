"""The only module that imports embreex: triangle scenes and batched ray queries.

embreex releases the GIL inside `run`, so worker threads trace concurrently.

Every scene is built by embreex. For the baker's compiled chunk call (`kernels.trace_chunk`)
a scene also offers its Embree handle and the addresses of ``rtcIntersect1`` and
``rtcOccluded1`` in the Embree library embreex loaded (`EmbreeCalls`): the call then
calls Embree per ray itself, with no Python between a chunk's rays. The handle is the
``scene_i`` field that embreex declares in its published Cython interface
(``embreex/rtcore_scene.pxd``); it is read only after the object's layout has been checked
against that declaration, and a scene whose layout does not match offers no handle (the
path tracer then uses `run`, as everywhere else).
"""

from __future__ import annotations

import ctypes
import functools
import gc
import itertools
import threading
import time
from concurrent.futures import Executor
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from embreex import rtcore, rtcore_scene
from embreex.mesh_construction import TriangleMesh

from isolume.baking.rays import RayStats
from isolume.volumes import cores
from isolume.volumes.cubes import PAD_BYTES, padded_copy

_MISS = -1


class RayRecorder:
    """Benchmarks: a copy of every ray a scene traces, to trace again on bare embreex.

    Copies go into buffers of each tracing thread that are reused from level to level
    (`clear`): holding on to the tracer's own arrays instead would keep the allocator from
    reusing their memory, and the tracer would pay page faults on fresh memory that a
    real bake never pays. A compiled chunk call writes its rays straight into the buffer
    (`reserve`, `commit`).
    """

    def __init__(self) -> None:
        self._local = threading.local()
        self._buffers: list[_RecordBuffer] = []
        self._lock = threading.Lock()

    def _buffer(self) -> _RecordBuffer:
        buffer = getattr(self._local, "buffer", None)
        if buffer is None:
            buffer = self._local.buffer = _RecordBuffer()
            with self._lock:
                self._buffers.append(buffer)
        return buffer

    def add(self, query: str, origins: np.ndarray, dirs: np.ndarray,
            dists: np.ndarray | None) -> None:
        """Copy one batch: (N, 3) float32 origins and directions, (N,) distances or None."""
        self._buffer().add(query, origins, dirs, dists)

    def reserve(self, count: int) -> np.ndarray:
        """Room for `count` rays of this thread: (count, `kernels.RAY_RECORD_ROWS`)
        float32 rows (origin, direction, 1 for an occlusion query, 0 for a closest hit)
        to be filled, then kept with `commit`."""
        return self._buffer().reserve(count)

    def commit(self, count: int) -> None:
        """Keep the first `count` rays written since this thread's last `reserve`."""
        self._buffer().commit(count)

    def batches(self) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
        """Every batch recorded since `clear`: (query, origins, dirs, dists or None)."""
        return [batch for buffer in self._buffers for batch in buffer.batches()]

    def clear(self) -> None:
        """Forget the batches; keep the buffers."""
        for buffer in self._buffers:
            buffer.used, buffer.spans = 0, []


class _RecordBuffer:
    """One thread's recorded rays: growing (capacity, 7) float32 rows of origin,
    direction and distance (or query kind), and the (query, start, stop, has distances)
    of each batch — query "TRACED" for the mixed rays of a compiled chunk call, whose
    last column tells their kind."""

    def __init__(self) -> None:
        self.rows = np.empty((0, 7), np.float32)
        self.used = 0
        self.spans: list[tuple[str, int, int, bool]] = []

    def reserve(self, n: int) -> np.ndarray:
        if self.used + n > len(self.rows):
            grown = np.empty((max(2 * len(self.rows), self.used + n), 7), np.float32)
            grown[:self.used] = self.rows[:self.used]
            self.rows = grown
        return self.rows[self.used:self.used + n]

    def commit(self, n: int) -> None:
        self.spans.append(("TRACED", self.used, self.used + n, False))
        self.used += n

    def add(self, query: str, origins, dirs, dists) -> None:
        n = len(origins)
        rows = self.reserve(n)
        rows[:, 0:3], rows[:, 3:6] = origins, dirs
        if dists is not None:
            rows[:, 6] = dists
        self.spans.append((query, self.used, self.used + n, dists is not None))
        self.used += n

    def batches(self) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
        out: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]] = []
        for query, lo, hi, has_dists in self.spans:
            rows = self.rows[lo:hi]
            if query != "TRACED":
                out.append((query, rows[:, 0:3], rows[:, 3:6],
                            rows[:, 6] if has_dists else None))
                continue
            for kind, traced in ((0, "INTERSECT"), (1, "OCCLUDED")):
                chosen = rows[rows[:, 6] == kind]
                if len(chosen):
                    out.append((traced, chosen[:, 0:3], chosen[:, 3:6], None))
        return out


class EmbreeCalls(NamedTuple):
    """What compiled code needs to trace rays in one committed scene: its ``RTCScene``
    handle and the addresses of ``rtcIntersect1`` and ``rtcOccluded1`` (integers)."""

    scene: int
    intersect: int
    occluded: int


@functools.cache
def _embree_library() -> ctypes.CDLL | None:
    """The Embree library that embreex loaded into this process (found in /proc/self/maps:
    the very instance that builds the scenes), or None where it cannot be found."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "libembree" in line}
    except OSError:
        return None
    if len(paths) != 1:
        return None
    return ctypes.CDLL(paths.pop())  # already loaded: the same handle, nothing re-read


@functools.cache
def _embree_functions() -> tuple[int, int] | None:
    """Addresses of ``rtcIntersect1`` and ``rtcOccluded1`` in embreex's Embree, or None."""
    lib = _embree_library()
    if lib is None:
        return None
    return (ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value,
            ctypes.cast(lib.rtcOccluded1, ctypes.c_void_p).value)


def _scene_handle(embree) -> int | None:
    """The ``RTCScene`` of an embreex ``EmbreeScene``, or None if its layout is not the
    one embreex declares: ``scene_i`` (a pointer), then ``public int is_committed``, then
    the device, right after the object header. Checked twice: the instance size, and the
    int after the pointer following the public attribute as it is set to two values."""
    header = object.__basicsize__  # reference count and type
    pointer = ctypes.sizeof(ctypes.c_void_p)
    if type(embree).__basicsize__ != header + 3 * pointer:
        return None
    field = ctypes.c_int.from_address(id(embree) + header + pointer)
    committed = embree.is_committed
    try:
        for value in (0x5A17, 0x0C3D):
            embree.is_committed = value
            if field.value != value:
                return None
    finally:
        embree.is_committed = committed
    return ctypes.c_void_p.from_address(id(embree) + header).value


_DEVICES: dict[int, object] = {}
_DEVICES_LOCK = threading.Lock()


def sized_device(threads: int) -> object:
    """An embreex ``EmbreeDevice`` whose Embree device builds with at most `threads`
    threads (``rtcNewDevice("threads=N")``; embreex makes its devices unconfigured, with
    every core), one per count, kept; None where its layout or the library cannot be
    verified (scenes then use embreex's own device).

    The device is the one field of embreex's ``EmbreeDevice`` (``embreex/rtcore.pxd``); it
    is replaced only after a scene made on the object has been asked for its device by
    Embree itself (``rtcGetSceneDevice``) and answered with that field's value."""
    with _DEVICES_LOCK:
        if threads not in _DEVICES:
            _DEVICES[threads] = _configured_device(f"threads={int(threads)}")
        return _DEVICES[threads]


def _configured_device(config: str):
    """`sized_device`'s device for the Embree configuration string `config`, or None."""
    lib = _embree_library()
    header, pointer = object.__basicsize__, ctypes.sizeof(ctypes.c_void_p)
    if lib is None or rtcore.EmbreeDevice.__basicsize__ != header + pointer:
        return None
    p = ctypes.c_void_p
    scene_device = _typed(lib, "rtcGetSceneDevice", p, p)
    release_device = _typed(lib, "rtcReleaseDevice", None, p)
    new_device = _typed(lib, "rtcNewDevice", p, ctypes.c_char_p)
    device = rtcore.EmbreeDevice()
    field = ctypes.c_void_p.from_address(id(device) + header)
    probe = rtcore_scene.EmbreeScene(device)
    handle = _scene_handle(probe)
    found = scene_device(handle) if handle else None
    if found:
        release_device(found)  # rtcGetSceneDevice retained it
    del probe
    if not found or found != field.value:
        return None
    release_device(field.value)  # first: Embree sizes a device by the largest alive
    made = new_device(config.encode())
    field.value = made or new_device(None)
    return device if made else None


def _new_scene():
    """An embreex scene on the device of `cores.embree_threads()` threads
    (`sized_device`), or on embreex's own where that cannot be made."""
    device = sized_device(cores.embree_threads())
    return rtcore_scene.EmbreeScene(device) if device is not None else rtcore_scene.EmbreeScene()


def embree_calls(scene: Scene) -> EmbreeCalls | None:
    """`EmbreeCalls` of a committed, non-empty `Scene`, or None (empty scene, or an
    embreex whose scene layout or library could not be verified)."""
    if scene.empty:
        return None
    functions, handle = _embree_functions(), _scene_handle(scene._scene)
    if functions is None or not handle:
        return None
    return EmbreeCalls(handle, *functions)


class Scene:
    """One triangle mesh in an Embree scene.

    Args:
        vertices: (V, 3) world positions.
        faces: (F, 3) vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.empty: bool = len(faces) == 0
        faces = np.asarray(faces)  # uint32 indices (< 2³¹) read as int32 without a copy
        self.faces: np.ndarray = padded(
            faces.view(np.int32) if faces.dtype == np.uint32 else faces, np.int32)
        self.vertices: np.ndarray = padded(vertices, np.float32)
        self.recorder: RayRecorder | None = None  # benchmarks: a copy of every batch
        self.built_by: str = ""
        """How the Embree scene was built: "native", "embreex", or "" (empty)."""
        self.mesh_seconds: float = 0.0
        """Seconds the mesh took to make (set by whoever made it)."""
        began = time.perf_counter()
        if not self.empty:
            self._scene = _new_scene()
            with cores.timed_item("bvh"):  # on Embree's own threads (`sized_device`)
                self.built_by = _attach_mesh(self._scene, self.vertices, self.faces)
        self.pieces: int = {"native": len(_pieces(len(faces))), "embreex": 1}.get(self.built_by, 0)
        """Embree scenes the triangles were built as (`PIECE_TRIANGLES`; 0 when empty)."""
        self.build_seconds: float = time.perf_counter() - began
        """Seconds Embree's geometry and BVH took to build."""
        self.calls: EmbreeCalls | None = embree_calls(self)
        """`EmbreeCalls` for compiled chunk calls, or None (then only `intersect` and
        `occluded` trace)."""

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, stats: RayStats | None = None
                  ) -> dict[str, np.ndarray]:
        """Closest hits of (N, 3) rays (float32 arrays of any strides are used as they are).

        Returns:
            dict with ``t`` (N,) distance, ``prim`` (N,) triangle id in its piece
            (`PIECE_TRIANGLES`; < 0: no hit), ``u``, ``v`` (N,) barycentrics, ``ng``
            (N, 3) unnormalised geometric normal.
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


# Embree 4 constants (embree4/rtcore_geometry.h, rtcore_buffer.h, rtcore_common.h).
_GEOMETRY_TRIANGLE, _GEOMETRY_INSTANCE = 0, 121
_BUFFER_INDEX, _BUFFER_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3, _FORMAT_FLOAT3X4_COLUMN_MAJOR = 0x5003, 0x9003, 0x9234
_BYTES_PER_ITEM = 12  # three 32-bit values per vertex and per triangle
_IDENTITY = np.array([1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0], np.float32)  # 3×4, by column

PIECE_TRIANGLES = 4_000_000
"""A mesh with more triangles is built as pieces of at most this many consecutive faces
(marching cubes emits them slab by slab, so a piece is a slab of the surface), each its own
Embree scene, instanced in the scene that is traced. Embree's build holds ~32 bytes per
triangle more than the finished BVH (~69 bytes per triangle); pieces built one after another
hold that for one piece at a time: on the 512³ foot CT's 13 M triangles the build's peak is
77 bytes per triangle instead of 101, and rays are traced as fast. A hit through an instance
can differ in the last bits of its distance and normal from the same hit in one scene, so
smaller meshes stay one scene."""


def padded(array: np.ndarray, dtype: npt.DTypeLike) -> np.ndarray:
    """`array` as a C-contiguous `dtype` array whose buffer goes on at least `PAD_BYTES`
    past its end, as Embree's shared buffers need (rtcSetSharedGeometryBuffer: the last
    element must be readable with 16-byte loads): `array` itself when its buffer does
    (`volumes.tracing_surface` and `volumes.isosurface` allocate so), else a
    `padded_copy`."""
    a = np.ascontiguousarray(array, dtype)
    base = a
    while isinstance(base.base, np.ndarray):
        base = base.base
    if base is not a and base.flags.c_contiguous and (
            a.ctypes.data + a.nbytes + PAD_BYTES <= base.ctypes.data + base.nbytes):
        return a
    return padded_copy(a, dtype)


class _NativeBuild(NamedTuple):
    """Embree's own scene-building functions, typed for ctypes (which releases the GIL
    around each call: the BVH build runs while other threads hold it)."""

    scene_device: ctypes._CFuncPtr
    new_geometry: ctypes._CFuncPtr
    shared_buffer: ctypes._CFuncPtr
    commit_geometry: ctypes._CFuncPtr
    attach: ctypes._CFuncPtr
    release_geometry: ctypes._CFuncPtr
    release_device: ctypes._CFuncPtr
    device_error: ctypes._CFuncPtr
    commit_scene: ctypes._CFuncPtr
    new_scene: ctypes._CFuncPtr
    release_scene: ctypes._CFuncPtr
    instanced_scene: ctypes._CFuncPtr
    transform: ctypes._CFuncPtr


def _typed(lib: ctypes.CDLL, name: str, restype, *argtypes):
    function = getattr(lib, name)
    function.restype, function.argtypes = restype, list(argtypes)
    return function


@functools.cache
def _native_build() -> _NativeBuild | None:
    """The Embree functions that build a triangle scene, or None where embreex's Embree
    cannot be found, lacks one, or builds a test scene that answers differently from the
    one embreex builds itself (`_native_matches_embreex`): scenes are then built by
    embreex alone."""
    lib = _embree_library()
    if lib is None:
        return None
    p, u = ctypes.c_void_p, ctypes.c_uint
    try:
        build = _NativeBuild(
            _typed(lib, "rtcGetSceneDevice", p, p),
            _typed(lib, "rtcNewGeometry", p, p, ctypes.c_int),
            _typed(lib, "rtcSetSharedGeometryBuffer", None, p, ctypes.c_int, u, ctypes.c_int,
                   p, ctypes.c_size_t, ctypes.c_size_t, ctypes.c_size_t),
            _typed(lib, "rtcCommitGeometry", None, p),
            _typed(lib, "rtcAttachGeometry", u, p, p),
            _typed(lib, "rtcReleaseGeometry", None, p),
            _typed(lib, "rtcReleaseDevice", None, p),
            _typed(lib, "rtcGetDeviceError", ctypes.c_int, p),
            _typed(lib, "rtcCommitScene", None, p),
            _typed(lib, "rtcNewScene", p, p),
            _typed(lib, "rtcReleaseScene", None, p),
            _typed(lib, "rtcSetGeometryInstancedScene", None, p, p),
            _typed(lib, "rtcSetGeometryTransform", None, p, u, ctypes.c_int, p),
        )
    except AttributeError:
        return None
    return build if _native_matches_embreex(build) else None


def _attach_native(build: _NativeBuild, scene, vertices: np.ndarray,
                   faces: np.ndarray) -> bool:
    """Give embreex's scene the triangles, made with Embree's own API — on the arrays
    themselves (shared buffers: no copy; they must outlive the scene and be `padded`), as
    instanced pieces where there are more than `PIECE_TRIANGLES` — and commit it (the BVH
    builds, without the GIL). embreex's `run` then finds the scene committed and traces it.

    Returns:
        False when the scene's handle cannot be verified or Embree reports an error.
    """
    handle = _scene_handle(scene)
    if not handle:
        return False
    device = build.scene_device(handle)
    if not device:
        return False
    try:
        pieces = _pieces(len(faces))
        if len(pieces) == 1:
            attached = _add_triangles(build, device, handle, vertices, faces, *pieces[0])
        else:
            attached = all(_add_piece(build, device, handle, vertices, faces, first, count)
                           for first, count in pieces)
        if not attached:
            return False
        build.commit_scene(handle)
        if build.device_error(device) != 0:
            return False
    finally:
        build.release_device(device)  # rtcGetSceneDevice retained it
    scene.is_committed = 1
    return True


def _pieces(triangles: int) -> list[tuple[int, int]]:
    """(first face, face count) of each piece of a mesh of `triangles` faces: as few as
    `PIECE_TRIANGLES` allows, of equal size to within one face."""
    bounds = np.linspace(0, triangles, -(-triangles // PIECE_TRIANGLES) + 1).astype(int)
    return [(int(a), int(b - a)) for a, b in itertools.pairwise(bounds)]


def _add_triangles(build: _NativeBuild, device: int, target: int, vertices: np.ndarray,
                   faces: np.ndarray, first: int, count: int) -> bool:
    """Attach to the Embree scene `target` a triangle geometry of the `count` faces from
    `first` on (indices into all of `vertices`). False when Embree reports an error."""
    geometry = build.new_geometry(device, _GEOMETRY_TRIANGLE)
    if not geometry:
        return False
    try:
        build.shared_buffer(geometry, _BUFFER_VERTEX, 0, _FORMAT_FLOAT3, vertices.ctypes.data,
                            0, _BYTES_PER_ITEM, len(vertices))
        build.shared_buffer(geometry, _BUFFER_INDEX, 0, _FORMAT_UINT3, faces.ctypes.data,
                            first * _BYTES_PER_ITEM, _BYTES_PER_ITEM, count)
        build.commit_geometry(geometry)
        if build.device_error(device) != 0:
            return False
        build.attach(target, geometry)
    finally:
        build.release_geometry(geometry)  # the scene holds its own reference
    return True


def _add_piece(build: _NativeBuild, device: int, target: int, vertices: np.ndarray,
               faces: np.ndarray, first: int, count: int) -> bool:
    """Build the `count` faces from `first` on as an Embree scene of their own (its BVH
    now, so that the build's temporary memory is freed before the next piece's) and attach
    an instance of it, untransformed, to the scene `target`. False on an Embree error."""
    piece = build.new_scene(device)
    if not piece:
        return False
    try:
        if not _add_triangles(build, device, piece, vertices, faces, first, count):
            return False
        build.commit_scene(piece)
        instance = build.new_geometry(device, _GEOMETRY_INSTANCE)
        if build.device_error(device) != 0 or not instance:
            return False
        try:
            build.instanced_scene(instance, piece)
            build.transform(instance, 0, _FORMAT_FLOAT3X4_COLUMN_MAJOR, _IDENTITY.ctypes.data)
            build.commit_geometry(instance)
            if build.device_error(device) != 0:
                return False
            build.attach(target, instance)
        finally:
            build.release_geometry(instance)
    finally:
        build.release_scene(piece)  # the instance holds its own reference
    return True


def _native_matches_embreex(build: _NativeBuild) -> bool:
    """Build a small test scene both ways and compare closest hits and occlusion of rays
    through it: the native build is used only if every answer is identical."""
    rng = np.random.default_rng(7)
    vertices = rng.uniform(-1, 1, (30, 3)).astype(np.float32)
    faces = rng.integers(0, 30, (20, 3)).astype(np.int32)
    origins = np.zeros((256, 3), np.float32)
    dirs = rng.normal(size=(256, 3)).astype(np.float32)
    reference = _new_scene()
    _attach_embreex(reference, vertices, faces)
    native = _new_scene()
    try:
        if not _attach_native(build, native, vertices, faces):
            return False
    except (OSError, ValueError):
        return False
    a, b = reference.run(origins, dirs, output=1), native.run(origins, dirs, output=1)
    same = all(np.array_equal(a[k], b[k]) for k in ("primID", "tfar", "u", "v", "Ng"))
    hits = a["primID"] >= 0
    return bool(same and hits.any() and (~hits).any() and np.array_equal(
        reference.run(origins, dirs, query="OCCLUDED"), native.run(origins, dirs,
                                                                   query="OCCLUDED")))


def _attach_mesh(scene, vertices: np.ndarray, faces: np.ndarray) -> str:
    """Give `scene` the (V, 3) float32 vertices and (F, 3) int32 faces of a mesh and build
    its BVH, by Embree's own API where it was verified (`_native_build`: 0.08 s for the
    580 k-triangle level of the engine CT), else through embreex (0.7 s).

    Returns:
        "native" or "embreex": how the scene was built.
    """
    build = _native_build()
    if build is not None and _attach_native(build, scene, vertices, faces):
        return "native"
    _attach_embreex(scene, vertices, faces)
    _build_bvh(scene)
    return "embreex"


def _attach_embreex(scene, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Give embreex the (V, 3) float32 vertices and (F, 3) int32 faces of a mesh.

    embreex copies them into Embree's buffers element by element with generic Python
    indexing (``vertices[i, k]``, ``faces[i][k]``): from numpy arrays every element first
    becomes a numpy scalar, and a row a view. From an object array of Python floats and an
    array of one list of ints per triangle it reads the same values three times faster
    (the garbage collector paused meanwhile: it would otherwise scan the half million new
    lists again and again). An embreex that refuses such arrays gets the numpy arrays.
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


def replay(scene: Scene,
           batches: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]],
           pool: Executor) -> tuple[int, float]:
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
