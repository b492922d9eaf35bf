"""`baking.trace`: the Embree scene against embreex used plainly, the compiled chunk call's own
Embree calls, and the ray recorder of ``isolume bench bake``."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from isolume import volumes
from isolume.baking import embree_kernels, trace
from isolume.baking.trace import RayRecorder, Scene, _scene_handle, replay


def _rays(mesh, count: int, seed: int):
    gen = np.random.default_rng(seed)
    centre = mesh.vertices.mean(axis=0)
    spread = mesh.vertices.std(axis=0)
    origins = (centre + gen.normal(size=(count, 3)) * spread).astype(np.float32)
    dirs = gen.normal(size=(count, 3)).astype(np.float32)
    return origins, dirs


@pytest.mark.parametrize("native", [True, False])
def test_scene_answers_exactly_as_embreex_given_numpy_arrays(native, monkeypatch):
    """The mesh reaches Embree by Embree's own API (`native`: the arrays shared, not
    copied, the BVH built without the GIL), or, where that is unavailable, through embreex from
    object arrays (a faster copy than numpy's): every hit, distance, barycentric and normal
    must equal those of a scene that embreex built from the numpy arrays."""
    if not native:
        monkeypatch.setattr(trace, "_native_build", lambda: None)
    mesh = volumes.isosurface(volumes.load("synthetic:engine:48"), 0.3, normals="none")
    scene = Scene(mesh.vertices, mesh.faces)
    assert scene.built_by == ("native" if native else "embreex")
    plain = rtcore_scene.EmbreeScene()
    TriangleMesh(plain, np.ascontiguousarray(mesh.vertices, np.float32),
                 np.ascontiguousarray(mesh.faces, np.int32))
    origins, dirs = _rays(mesh, 20000, 1)
    got = scene.intersect(origins, dirs)
    want = plain.run(origins, dirs, output=1)
    assert 0.2 < np.mean(got["prim"] >= 0) < 0.95  # both hits and misses are compared
    for key, theirs in (("prim", "primID"), ("t", "tfar"), ("u", "u"), ("v", "v"),
                        ("ng", "Ng")):
        np.testing.assert_array_equal(got[key], want[theirs])
    np.testing.assert_array_equal(scene.occluded(origins, dirs),
                                  plain.run(origins, dirs, query="OCCLUDED") != -1)


def test_embree_shares_padded_arrays_and_copies_the_others_padded():
    """Embree reads 16 bytes at a shared buffer's last element: the tracing surface's and
    the marching-cubes mesh's arrays are allocated with room after them and shared as
    they are (uint32 faces read as int32); other arrays are copied once into padded
    buffers."""
    volume = volumes.load("synthetic:engine:48")
    vertices, faces = volumes.tracing_surface(volume, 0.3)
    scene = Scene(vertices, faces)
    assert scene.vertices is vertices and scene.faces is faces
    mesh = volumes.isosurface(volume, 0.3, normals="none")
    scene = Scene(mesh.vertices, mesh.faces)
    assert scene.vertices is mesh.vertices and np.shares_memory(scene.faces, mesh.faces)
    for array, dtype in ((np.array(mesh.vertices), np.float32),
                         (np.array(mesh.faces), np.int32)):
        copy = trace.padded(array, dtype)
        assert copy is not array and copy.dtype == dtype
        np.testing.assert_array_equal(copy, array)
        room = copy.base.nbytes - copy.nbytes
        assert room >= trace.PAD_BYTES and trace.padded(copy, dtype) is copy
    inner = np.array(vertices)[:-2]  # a view that ends inside its buffer, 24 bytes early
    assert trace.padded(inner, np.float32) is inner


def test_strided_rays_are_traced_as_contiguous_ones():
    """The path tracer hands Embree transposed (3, N) rows: the same answers."""
    mesh = volumes.isosurface(volumes.load("synthetic:torus:32"), 0.5, normals="none")
    scene = Scene(mesh.vertices, mesh.faces)
    origins, dirs = _rays(mesh, 5000, 2)
    rows_o, rows_d = np.ascontiguousarray(origins.T), np.ascontiguousarray(dirs.T)
    got, want = scene.intersect(rows_o.T, rows_d.T), scene.intersect(origins, dirs)
    for key in ("prim", "t", "ng"):
        np.testing.assert_array_equal(got[key], want[key])


def test_recorder_keeps_exact_copies_from_every_thread_and_replays_them():
    mesh = volumes.isosurface(volumes.load("synthetic:torus:32"), 0.5, normals="none")
    scene = Scene(mesh.vertices, mesh.faces)
    recorder = RayRecorder()
    scene.recorder = recorder
    batches = [_rays(mesh, n, seed) for seed, n in enumerate((700, 1300, 50, 2000))]
    dists = np.linspace(0.1, 3.0, 1300).astype(np.float32)

    def trace(i):
        origins, dirs = batches[i]
        if i == 1:
            scene.occluded(np.ascontiguousarray(origins.T).T, dirs, dists)
        else:
            scene.intersect(origins, dirs)

    with ThreadPoolExecutor(max_workers=2) as pool:
        list(pool.map(trace, range(len(batches))))
        recorded = recorder.batches()
        assert sorted(len(b[1]) for b in recorded) == [50, 700, 1300, 2000]
        for query, origins, dirs, d in recorded:
            i = [len(b[0]) for b in batches].index(len(origins))
            np.testing.assert_array_equal(origins, batches[i][0])
            np.testing.assert_array_equal(dirs, batches[i][1])
            assert query == ("OCCLUDED" if i == 1 else "INTERSECT")
            if i == 1:  # the distance limit is kept (clamped as Scene.occluded does)
                np.testing.assert_array_equal(d, dists)
            else:
                assert d is None
        rays, seconds = replay(scene, recorded, pool)
        assert rays == 4050 and seconds > 0
    recorder.clear()
    assert recorder.batches() == []
    scene.intersect(*batches[2])  # buffers are reused after clear
    assert [len(b[1]) for b in recorder.batches()] == [50]


def test_scenes_offer_embree_calls_that_answer_as_embreex():
    """The compiled chunk call's own Embree calls (the handle read from embreex's scene, the
    functions of the library embreex loaded) give embreex's answers, hits and misses."""
    mesh = volumes.isosurface(volumes.load("synthetic:engine:48"), 0.3, normals="none")
    scene = Scene(mesh.vertices, mesh.faces)
    assert scene.calls is not None, "this embreex's scene layout should be recognised"
    assert scene._scene.is_committed == 1  # the layout check leaves the attribute as it was
    origins, dirs = _rays(mesh, 20000, 3)
    calls = tuple(scene.calls)
    rows_o, rows_d = np.ascontiguousarray(origins.T), np.ascontiguousarray(dirs.T)
    t, prim, ng = embree_kernels.intersect_rays(calls, rows_o, rows_d)
    want = scene._scene.run(origins, dirs, output=1)
    assert 0.2 < np.mean(prim >= 0) < 0.95
    np.testing.assert_array_equal(prim, want["primID"])
    hit = prim >= 0
    np.testing.assert_array_equal(t[hit], want["tfar"][hit])
    np.testing.assert_array_equal(ng[hit], want["Ng"][hit])
    np.testing.assert_array_equal(embree_kernels.occluded_rays(calls, rows_o, rows_d),
                                  scene._scene.run(origins, dirs, query="OCCLUDED") != -1)


def test_a_large_mesh_is_built_as_instanced_pieces_that_answer_as_one_scene(monkeypatch):
    """Above `PIECE_TRIANGLES` the mesh becomes slabs of consecutive faces, each an Embree
    scene of its own, instanced untransformed: the same rays hit and miss, both through
    embreex's `run` and through the compiled chunk call's Embree calls; distances and
    normals agree to float32 rounding (the instance's ray transform)."""
    mesh = volumes.isosurface(volumes.load("synthetic:engine:48"), 0.3, normals="none")
    limit = trace.PIECE_TRIANGLES
    for faces, count in ((10, 1), (limit, 1), (limit + 1, 2), (2 * limit + 1, 3)):
        pieces = trace._pieces(faces)
        assert len(pieces) == count and max(n for _, n in pieces) <= limit
        counts = [n for _, n in pieces]
        assert [first for first, _ in pieces] == list(np.cumsum([0, *counts[:-1]]))
        assert sum(n for _, n in pieces) == faces
    whole = Scene(mesh.vertices, mesh.faces)
    monkeypatch.setattr(trace, "PIECE_TRIANGLES", len(mesh.faces) // 3 + 1)
    pieces = Scene(mesh.vertices, mesh.faces)
    assert (whole.pieces, pieces.pieces) == (1, 3) and pieces.built_by == "native"
    origins, dirs = _rays(mesh, 20000, 4)
    want = whole.intersect(origins, dirs)
    rows_o, rows_d = np.ascontiguousarray(origins.T), np.ascontiguousarray(dirs.T)
    t, prim, ng = embree_kernels.intersect_rays(tuple(pieces.calls), rows_o, rows_d)
    for got in (pieces.intersect(origins, dirs), {"prim": prim, "t": t, "ng": ng}):
        hit = want["prim"] >= 0
        assert 0.2 < hit.mean() < 0.95
        np.testing.assert_array_equal(got["prim"] >= 0, hit)
        np.testing.assert_allclose(got["t"][hit], want["t"][hit], rtol=1e-5)
        np.testing.assert_allclose(got["ng"][hit], want["ng"][hit], rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(pieces.occluded(origins, dirs), whole.occluded(origins, dirs))
    np.testing.assert_array_equal(embree_kernels.occluded_rays(tuple(pieces.calls), rows_o,
                                                               rows_d),
                                  whole.occluded(origins, dirs))


def test_scene_handle_is_refused_for_another_layout():
    """Only an object laid out as embreex declares EmbreeScene gives a handle."""

    class Lookalike:  # the public attribute, but a dict and weak references after it
        is_committed = 1

    assert _scene_handle(Lookalike()) is None
    assert Scene(np.zeros((0, 3)), np.zeros((0, 3), np.int32)).calls is None  # empty


def test_recorder_splits_a_compiled_loop_s_rays_by_query():
    recorder = RayRecorder()
    rows = recorder.reserve(5)
    rows[:, :6] = np.arange(30, dtype=np.float32).reshape(5, 6)
    rows[:, 6] = [0, 1, 1, 0, 1]
    recorder.commit(4)  # the fifth was reserved but not traced
    batches = {query: (o, d, dist) for query, o, d, dist in recorder.batches()}
    np.testing.assert_array_equal(batches["INTERSECT"][0], rows[[0, 3], 0:3])
    np.testing.assert_array_equal(batches["OCCLUDED"][1], rows[[1, 2], 3:6])
    assert batches["OCCLUDED"][2] is None


def test_bench_bake_times_a_plain_bake_and_replays_the_same_rays(tmp_path, capsys):
    """`isolume bench bake`: the timed bake and the recorded one trace the same rays (it
    asserts so), and every figure it prints is there and consistent."""
    import json

    from isolume.app.cli import main

    out = tmp_path / "bench.json"
    assert main(["bench", "bake", "synthetic:torus:24", "--samples", "2", "--bounces", "1",
                 "--workers", "2", "--json", str(out)]) == 0
    f = json.loads(out.read_text())
    assert f["rays"] > 0 and f["levels"] >= 2
    assert f["end_to_end_seconds"] == pytest.approx(f["plan_seconds"] + f["bake_seconds"])
    assert 0 < f["end_to_end_ratio"] < f["ratio"]
    assert f["bare_embreex_rays_per_s"] > 0 and f["chunk_ratio"] > 0
    assert "end to end" in capsys.readouterr().out
