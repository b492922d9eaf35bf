"""The irradiance baker against analytic answers (tolerances derived, not guessed)."""

import dataclasses
import importlib
import itertools

import numpy as np
import pytest

from isolume import volumes
from isolume.baking import BakeConfig, BakeError, Lattice, bake
from isolume.baking.lattice import LatticeGeometry
from isolume.volumes import Volume
from isolume.volumes.errors import WriteError
from isolume.volumes.synthetic import SPHERE_RADIUS, make


def _sdf_volume(sdf, size=48, extent=1.0, name="test"):
    """Volume of density 0.5 - 0.5 tanh(sdf / w) on a cube of `extent`, w = 1.2 voxels."""
    h = extent / (size - 1)
    axis = (np.arange(size) - (size - 1) / 2) * h
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    data = 0.5 - 0.5 * np.tanh(sdf(x, y, z) / (1.2 * h))
    return Volume(data.astype(np.float32), (h, h, h), (axis[0],) * 3, name=name, source=name)


def _baked(lattice: Lattice):
    """(N, 3) world centres and (N, C) values of the computed texels."""
    ids = np.flatnonzero(lattice.samples > 0)
    centres = lattice.geometry.centres(ids)
    return centres, lattice.values.reshape(-1, lattice.values.shape[-1])[ids]


def _surface_points(lattice: Lattice, volume: Volume, iso: float = 0.5):
    """Texels whose own isovalue is near `iso` (their surface is the one we know)."""
    centres, values = _baked(lattice)
    rho = volumes.value_at(volume, centres)
    near = np.abs(rho - iso) < 0.2
    return centres[near], values[near]


def test_unoccluded_convex_surface_sees_pi_times_sky():
    """Every texel on a convex surface under a uniform sky L: E = πL exactly, whatever the
    bounce count (no path can hit the surface again). Cosine sampling of a constant sky
    has zero variance, so any shortfall would be self-shadowing from the ray offset."""
    sky = np.array([1.0, 0.5, 0.25])
    config = BakeConfig(samples=16, bounces=2, env="constant:1,0.5,0.25")
    lattice = bake(make("sphere", 32), config, workers=2)
    _, values = _baked(lattice)
    assert len(values) > 1000
    np.testing.assert_allclose(values, np.broadcast_to(np.pi * sky, values.shape), rtol=1e-5)


def test_directional_light_cosine_and_shadow():
    """E = E0 max(0, n.l) on a sphere, and zero in the umbra of a second sphere.

    Hard shadows have no noise (one shadow ray per light). The texel normal is the
    smoothed gradient, within 1 degree of the analytic normal (test_isosurface), so
    |dE| <= E0 sin(1 deg) = 0.0175 E0 away from the terminator.
    """
    big, small = (0.0, 0.0, -0.1), (0.0, 0.0, 0.28)

    def sdf(x, y, z):
        d1 = np.sqrt((x - big[0]) ** 2 + (y - big[1]) ** 2 + (z - big[2]) ** 2) - 0.25
        d2 = np.sqrt((x - small[0]) ** 2 + (y - small[1]) ** 2 + (z - small[2]) ** 2) - 0.06
        return np.minimum(d1, d2)

    vol = _sdf_volume(sdf, size=64)
    e0 = 2.0
    config = BakeConfig(samples=2, bounces=0, env="", lights=("dir:0,0,1:2,2,2",),
                        direct_light="lattice")
    lattice = bake(vol, config, workers=2)
    points, values = _surface_points(lattice, vol)
    on_big = np.linalg.norm(points - big, axis=1) < 0.25 + 0.1
    points, values = points[on_big], values[on_big, 0]
    radial = (points - big) / np.linalg.norm(points - big, axis=1, keepdims=True)
    cos = radial[:, 2]
    # umbra: the small sphere's shadow cylinder (radius 0.06) along z, with a margin of the
    # texel offset and 1.5 voxels for the polygonal silhouettes
    h = vol.spacing[0]
    axis_dist = np.hypot(points[:, 0] - small[0], points[:, 1] - small[1])
    umbra = (axis_dist < 0.06 - 1.5 * h) & (cos > 0)
    lit = (axis_dist > 0.06 + 2.5 * h) & (cos > 0.2)
    assert umbra.sum() > 5 and lit.sum() > 100
    assert np.all(values[umbra] == 0.0)
    np.testing.assert_allclose(values[lit], e0 * cos[lit], atol=0.0175 * e0)
    assert np.all(values[cos < -0.2] == 0.0)  # facing away from the light


def test_point_light_inverse_square_and_cosine_on_a_plane():
    """Plane z = 0 (material below), point light I at height d: E = I (d - z) / r^3.

    A texel's paths start on its two bracketing level planes z(L) = w atanh(1 - 2L) (the
    field is 0.5 - 0.5 tanh(z / w)) plus the 0.25-voxel offset; the expected value mixes the
    two planes with the texel's own sample split. Tolerance: the trilinear field places a
    level within 0.02 voxel of the analytic plane (test_isosurface), and
    |d ln E / dz| <= 3 / (d - z) = 10 / world unit here, so 0.5 %; 1 % for the worst texel.
    Texels lit on the normals' side (the plane's top; it spans the box, so `baking.sides`
    would light its underside too, on alternate texels).
    """
    from isolume.baking.plan import make_plan

    vol = _sdf_volume(lambda x, y, z: z, size=40)
    d, intensity, samples = 0.3, 0.5, 32
    config = BakeConfig(samples=samples, bounces=0, env="",
                        lights=(f"point:0,0,{d}:{intensity},{intensity},{intensity}",),
                        iso_range=(0.3, 0.7), direct_light="lattice", sides="normals")
    lattice = bake(vol, config, workers=2)
    plan = make_plan(vol, lattice.geometry, config)
    h, width = vol.spacing[0], 1.2 * vol.spacing[0]
    centres = lattice.geometry.centres(plan.ids)
    values = lattice.values.reshape(-1, 3)[plan.ids, 0]

    def irradiance_on_level(level):
        z = width * np.arctanh(1 - 2 * level) + 0.25 * h
        r = np.sqrt(centres[:, 0] ** 2 + centres[:, 1] ** 2 + (d - z) ** 2)
        return intensity * (d - z) / r**3

    expected = _level_mix(plan, samples, irradiance_on_level)
    inner = np.abs(plan.rho - 0.5) < 0.4  # away from the flat tanh tails
    assert inner.sum() > 500
    relative = np.abs(values[inner] / expected[inner] - 1)
    assert np.median(relative) < 5e-3 and relative.max() < 1e-2
    assert expected[inner].max() / expected[inner].min() > 3  # falloff is really tested


def _level_mix(plan, samples, value_on_level):
    """Expected texel values: each texel's stratified sample split between its two levels,
    applied to `value_on_level(levels (T,)) -> (T,)`."""
    positions = np.arange(len(plan.ids))
    upper = sum(plan.on_upper(positions, np.full(len(positions), j)).astype(float)
                for j in range(samples)) / samples
    return ((1 - upper) * value_on_level(plan.levels[plan.lower])
            + upper * value_on_level(plan.levels[plan.lower + 1]))


@pytest.mark.parametrize("bounces", [0, 1, 3])
def test_closed_cavity_follows_the_geometric_series(bounces):
    """White-furnace-style: a point light I at the centre of a closed spherical cavity.

    A path starts on its level sphere of radius r_L (offset 0.25 voxel inwards) and sees
    the light at normal incidence: I / (r_L - 0.25 h)^2. Every bounce lands on the same
    closed sphere and again sees the light head-on: a^k I / r_L^2 for bounce k. So
    E_B = I/(r_L - 0.25h)^2 + I/r_L^2 * sum_{k=1..B} a^k, with no noise at all. Errors:
    level spheres within 0.02 voxel (test_isosurface) and Newton steps stopped within
    0.1 level spacing <= 0.05 voxel (max_move 0.5): 2 * 0.07 h / R = 0.6 % for the start
    point, and again 2 * 0.02 h / R = 0.2 % for each bounce vertex on the mesh: 1 % at worst.
    Texels lit on the normals' side, inside the cavity (seen from outside the box is its
    other side, which `baking.sides` would light).
    """
    from isolume.baking.plan import make_plan

    radius, albedo, intensity, samples = 0.3, 0.7, 0.09, 8
    vol = _sdf_volume(lambda x, y, z: radius - np.sqrt(x * x + y * y + z * z), size=48)
    config = BakeConfig(samples=samples, bounces=bounces, albedo=(albedo,) * 3, env="",
                        lights=(f"point:0,0,0:{intensity},{intensity},{intensity}",),
                        iso_range=(0.4, 0.6), direct_light="lattice", sides="normals")
    lattice = bake(vol, config, workers=2)
    plan = make_plan(vol, lattice.geometry, config)
    h, width = vol.spacing[0], 1.2 * vol.spacing[0]
    values = lattice.values.reshape(-1, 3)[plan.ids, 0]
    series = sum(albedo**k for k in range(1, bounces + 1))

    def on_level(level):
        r_level = radius - width * np.arctanh(1 - 2 * level)
        return intensity / (r_level - 0.25 * h) ** 2 + series * intensity / r_level**2

    expected = _level_mix(plan, samples, on_level)
    inner = np.abs(plan.rho - 0.5) < 0.3
    relative = np.abs(values[inner] / expected[inner] - 1)
    assert np.median(relative) < 5e-3 and np.percentile(relative, 99) < 1e-2
    # and the series itself: mean over texels against I/R^2 (1 + a + ... + a^B)
    total = intensity / radius**2 * (1 + series)
    assert abs(np.median(values[inner]) / total - 1) < 0.05


def test_determinism_across_worker_counts():
    config = BakeConfig(samples=24, bounces=1, env="sky:sun=3")
    vol = make("torus", 28)
    one = bake(vol, config, workers=1)
    two = bake(vol, config, workers=2)
    np.testing.assert_array_equal(one.values, two.values)
    np.testing.assert_array_equal(one.samples, two.samples)
    other_seed = bake(vol, dataclasses.replace(config, seed=1), workers=2)
    assert not np.array_equal(one.values, other_seed.values)


def test_a_bake_holds_one_group_of_sums_and_one_scene(monkeypatch):
    """What bounds a bake's memory: it traces one level at a time, so with no memory for
    scenes kept between passes one level scene is alive, the side probes' included
    (`ThreadBackend`'s cache makes room before a build);
    pass sums exist for one group of texels between their two levels (those of one lower
    level), and texels are committed a batch at a time (`backend.TEXELS_PER_BATCH`) — and
    batches of any size give the same lattice to the bit."""
    import weakref

    from isolume.baking import backend, passes
    from isolume.baking.plan import make_plan
    from isolume.baking.trace import Scene

    vol, config = make("engine", 36), BakeConfig(samples=4, bounces=1)
    whole = bake(vol, config, workers=2)
    plan = make_plan(vol, LatticeGeometry.for_volume(vol, config.scale), config)
    largest_group = int(np.bincount(plan.lower).max())
    most = {"sums": 0, "scenes": 0}
    alive = weakref.WeakSet()
    make_sums, init = passes.PassSums.__init__, Scene.__init__

    def sums(self, count, channels):
        make_sums(self, count, channels)
        most["sums"] = max(most["sums"], count)

    def scene(self, *args, **kwargs):
        init(self, *args, **kwargs)
        alive.add(self)
        most["scenes"] = max(most["scenes"], len(alive))

    monkeypatch.setattr(passes.PassSums, "__init__", sums)
    monkeypatch.setattr(Scene, "__init__", scene)
    monkeypatch.setattr(backend, "TEXELS_PER_BATCH", 37)
    baking_bake = importlib.import_module("isolume.baking.bake")  # `baking.bake` is the function
    commit_sums, commits = baking_bake.commit_sums, []
    monkeypatch.setattr(baking_bake, "commit_sums",
                        lambda lattice, ids, acc, slots: commits.append(len(ids))
                        or commit_sums(lattice, ids, acc, slots))
    batched = bake(vol, config, workers=2, scene_memory=0)
    assert len(batched.meta["plan"]["levels"]) >= 4
    assert most["sums"] == largest_group > 37
    assert most["scenes"] == 1
    assert max(commits) == 37 and sum(commits) == np.count_nonzero(whole.samples)
    np.testing.assert_array_equal(batched.values, whole.values)
    np.testing.assert_array_equal(batched.second, whole.second)
    np.testing.assert_array_equal(batched.samples, whole.samples)


@pytest.mark.parametrize("workers", [1, 2])
def test_the_tracing_starts_on_the_scene_the_side_probes_left(monkeypatch, workers):
    """The side probes go down the levels from the top one (built beside the plan), so the
    lowest level's scene, where the tracing starts, is built once for both: with one scene
    at a time (``scene_memory=0``, the default of a bake of `samples` paths a texel) a
    bake of K levels builds 2K − 1 scenes, not 2K; with memory for them all, K."""
    from isolume.baking import backend

    built, build = [], backend.level_scene

    def level_scene(volume, iso, config):
        built.append(iso)
        return build(volume, iso, config)

    monkeypatch.setattr(backend, "level_scene", level_scene)
    config = BakeConfig(samples=4, bounces=1)
    lattice = bake(make("engine", 36), config, workers=workers)
    levels = list(lattice.meta["plan"]["levels"])
    k = len(levels)
    assert k >= 4
    assert built == levels[::-1] + levels[1:]  # 2K − 1 builds
    built.clear()
    again = bake(make("engine", 36), config, workers=workers, scene_memory=1e9)
    assert built == levels[::-1]  # K builds: the tracing takes the probes' scenes
    np.testing.assert_array_equal(again.values, lattice.values)
    built.clear()  # with no side probed, the lowest level is built ahead, for the tracing
    lattice = bake(make("engine", 36), BakeConfig(samples=4, bounces=1, sides="normals"),
                   workers=workers, scene_memory=0)
    assert built == list(lattice.meta["plan"]["levels"])


def test_a_levels_next_step_is_queued_before_this_ones_chunks_are_collected(monkeypatch):
    """On a level, the step after this one (other texels, other rows of the sums) has its
    chunks queued before this step's are collected, so no worker waits for a step's last
    chunk while the level has work; across levels each step is collected before the next
    is queued (the next level's upper step adds to the same texels). The lattice is the
    same as with every step collected first."""
    from isolume.baking import backend

    log = []
    submit, collect = backend.ThreadBackend._submit_level, backend.ThreadBackend._collect

    def submitted(self, lay, sums, batch):
        log.append(("submit", lay.step.level, batch))
        return submit(self, lay, sums, batch)

    def collected(self, chunks, level, report):
        log.append(("collect", level, None))
        return collect(self, chunks, level, report)

    monkeypatch.setattr(backend.ThreadBackend, "_submit_level", submitted)
    monkeypatch.setattr(backend.ThreadBackend, "_collect", collected)
    config = BakeConfig(samples=4, bounces=1)
    lattice = bake(make("engine", 36), config, workers=2)
    queued = 0
    overlapped = []
    for kind, level, _batch in log:
        queued += 1 if kind == "submit" else -1
        assert 0 <= queued <= 2
        if kind == "submit" and queued == 2:
            overlapped.append(level)
    assert overlapped and len(overlapped) < len(lattice.meta["plan"]["levels"])
    submits = [(level, batch) for kind, level, batch in log if kind == "submit"]
    for (level, batch), (after, after_batch) in itertools.pairwise(submits):
        if after_batch == batch:  # one timeline batch: queued side by side, one level
            assert after == level
    monkeypatch.setattr(backend.ThreadBackend, "_submit_level", submit)

    def one_at_a_time(self, lay, sums, batch):  # each step collected before the next
        chunks = submit(self, lay, sums, batch)
        for chunk in chunks:
            chunk.result()
        return chunks

    monkeypatch.setattr(backend.ThreadBackend, "_submit_level", one_at_a_time)
    alone = bake(make("engine", 36), config, workers=2)
    np.testing.assert_array_equal(alone.values, lattice.values)
    np.testing.assert_array_equal(alone.second, lattice.second)
    np.testing.assert_array_equal(alone.samples, lattice.samples)


@pytest.mark.parametrize("memory, kept, builds", [
    (0, [], 8), (250, [1, 0, 3], 4), (1000, [1, 0, 3, 2], 4)])
def test_scenes_are_kept_first_come_within_their_memory(monkeypatch, memory, kept, builds):
    """`ThreadBackend._scene`: the first scenes built that fit in the memory (by
    `scene_bytes`; an empty one too where there is memory) are kept for good, the others
    cached one at a time (least recently used out: level 2's, too large to keep, stays
    cached while the others are kept); without memory, one scene is alive, an empty one
    included, and every scene is built again on the second round."""
    from types import SimpleNamespace

    from isolume.baking import backend

    triangles = {0: 0, 1: 1, 2: 3, 3: 1}  # level: triangles (100 bytes each)
    built = []

    def level_scene(volume, iso, config):
        built.append(int(iso))
        return SimpleNamespace(faces=np.zeros((triangles[int(iso)], 3)), mesh_seconds=0.0,
                               build_seconds=0.0)

    monkeypatch.setattr(backend, "level_scene", level_scene)
    threads = backend.ThreadBackend(1, scene_memory=memory)
    threads._levels, threads._stats = np.arange(4.0), backend.BakeStats()
    try:
        for level in [1, 0, 3, 2, 1, 0, 3, 2]:
            assert threads._scene(level) is threads._scene(level)
            assert len(threads._scenes) <= 1
        assert list(threads._kept) == kept
        assert sum(backend.scene_bytes(k) for k in threads._kept.values()) <= memory
        assert built == ([1, 0, 3, 2] * 2)[:builds]
    finally:
        threads.close()


def test_every_pass_of_a_bake_takes_the_scenes_kept_within_their_memory(monkeypatch):
    """A bake to a texel error traces in several passes over the levels (nodes, fine
    bricks, strays, dark texels); the scenes its memory holds are built once for all of
    them and the plan's side probes. A memory for two of its largest scenes holds no more
    than that beside the one traced, and one more while one is built (`scene_bytes`); the
    scenes it keeps are found by every later pass, so fewer are built than with none
    kept; and the lattice is the same bits whatever the memory."""
    import weakref

    from isolume.baking import backend
    from isolume.baking.trace import Scene

    built, alive, most = [], weakref.WeakSet(), {"bytes": 0}
    build, init = backend.level_scene, Scene.__init__

    def level_scene(volume, iso, config):
        built.append(iso)
        return build(volume, iso, config)

    def scene(self, *args, **kwargs):
        init(self, *args, **kwargs)
        alive.add(self)
        most["bytes"] = max(most["bytes"], sum(map(backend.scene_bytes, alive)))

    monkeypatch.setattr(backend, "level_scene", level_scene)
    monkeypatch.setattr(Scene, "__init__", scene)
    vol = make("engine", 36)
    config = BakeConfig(samples=8, bounces=1, texel_error=0.02)
    kept = bake(vol, config, workers=2, dense=False)
    levels = list(kept.meta["plan"]["levels"])
    assert len(levels) >= 4 and kept.meta["filled"]["filled"] > 0
    assert sorted(built) == sorted(levels)  # each level once
    largest = max(backend.scene_bytes(build(vol, iso, config)) for iso in levels)
    built.clear()
    alive.clear()
    most["bytes"] = 0
    two = bake(vol, config, workers=2, dense=False, scene_memory=2 * largest)
    some = len(built)
    assert some > len(levels)  # rebuilt in later passes
    assert largest < most["bytes"] <= 4 * largest
    built.clear()
    one = bake(vol, config, workers=2, dense=False, scene_memory=0)
    assert len(built) > some + 2
    for lattice in (two, one):
        np.testing.assert_array_equal(lattice.values, kept.values)
        np.testing.assert_array_equal(lattice.samples, kept.samples)


@pytest.mark.parametrize("env, albedo, direct", [
    ("constant:1,0.6,0.3", (0.8, 0.5, 0.3), None), ("sky:sun=3", (0.7, 0.7, 0.7), "pixels"),
    ("sky:sun=3", (0.7, 0.7, 0.7), "lattice")])
def test_whole_path_loop_equals_the_vertex_by_vertex_tracer(monkeypatch, env, albedo,
                                                            direct):
    """Chunks traced in one compiled call (Embree called per ray from compiled code) give
    the lattice of the tracer that calls embreex once per step, to the bit, and trace as
    many rays."""
    from isolume.baking import passes

    baking_bake = importlib.import_module("isolume.baking.bake")  # `baking.bake` is the function
    config = BakeConfig(samples=12, bounces=2, env=env, albedo=albedo, direct_light=direct)
    vol = make("engine", 40)
    used = []
    loop = passes.trace_whole_paths
    monkeypatch.setattr(passes, "trace_whole_paths",
                        lambda *args: used.append(1) or loop(*args))
    whole = bake(vol, config, workers=2)
    assert used, "the whole-path loop should cover this bake"
    monkeypatch.setattr(baking_bake, "whole_paths", lambda lighting, settings: None)
    stepwise = bake(vol, config, workers=2)
    assert np.count_nonzero(whole.samples) > 1000
    np.testing.assert_array_equal(whole.values, stepwise.values)
    np.testing.assert_array_equal(whole.second, stepwise.second)
    np.testing.assert_array_equal(whole.samples, stepwise.samples)
    assert whole.meta["rays_traced"] == stepwise.meta["rays_traced"]


def test_resume_equals_uninterrupted(tmp_path):
    """Samples added to a file later equal a bake that had them from the start, when the
    levels do not depend on the samples (an explicit max_move)."""
    config = BakeConfig(samples=40, bounces=1, env="constant:1,1,1", max_move=0.5)
    vol = make("shells", 32)
    whole = bake(vol, config, workers=2)
    path = tmp_path / "l.npz"
    bake(vol, dataclasses.replace(config, samples=15), out=path, workers=2)
    resumed = bake(vol, config, out=path, workers=1)
    assert (resumed.samples[whole.samples > 0] == 40).all()
    np.testing.assert_allclose(resumed.values, whole.values, rtol=2e-6, atol=1e-6)
    again = Lattice.load(path, vol)
    np.testing.assert_array_equal(again.values, resumed.values)
    assert again.meta["rays_traced"] == whole.meta["rays_traced"]


def test_more_paths_for_a_file_keep_its_plan(tmp_path):
    """A file baked with 8 paths a texel and resumed with 32 (whose own plan would move
    texels less far onto the levels, `plan.move_limit`) keeps its file's levels and move
    limit, so every texel's new paths start where its first ones did: the same plan
    record (levels, limit, texels left unreachable or lit on the high side; with the
    limit of 32 paths, 294 texels are left unreachable against the file's 253). The
    outlook counts the texels resumed."""
    from isolume.baking.bake import BakeOutlook
    from isolume.baking.plan import move_limit

    config = BakeConfig(samples=8, bounces=1, env="sky:sun=3")
    vol = make("engine", 32)
    path = tmp_path / "l.npz"
    first = bake(vol, config, out=path, workers=2)
    told: list[BakeOutlook] = []
    more = bake(vol, dataclasses.replace(config, samples=32), out=path, workers=2,
                outlook=told.append)
    keys = ("levels", "move_limit_voxels", "unreachable_texels", "high_side_texels")
    assert {k: more.meta["plan"][k] for k in keys} == {k: first.meta["plan"][k] for k in keys}
    assert told[0].resumed == np.count_nonzero(first.samples) > 0
    assert (more.samples[first.samples > 0] == 32).all()
    assert first.meta["plan"]["move_limit_voxels"] != pytest.approx(
        move_limit(dataclasses.replace(config, samples=32)))
    bake(vol, config, out=tmp_path / "new.npz", workers=2, outlook=told.append)
    assert told[1].resumed == 0


def test_a_file_of_other_settings_is_refused_naming_them(tmp_path):
    config = BakeConfig(samples=4, bounces=1, env="constant:1,1,1", max_move=0.5)
    vol = make("shells", 24)
    path = tmp_path / "l.npz"
    bake(vol, config, out=path, workers=2)
    with pytest.raises(BakeError, match=r"--bounces: 1 in the file, 2 here; --seed: 0 in "
                                        r"the file, 5 here\); to resume, repeat them"):
        bake(vol, dataclasses.replace(config, bounces=2, seed=5), out=path, workers=2)
    bake(vol, dataclasses.replace(config, samples=6), out=path, workers=2)  # more paths: on
    # an irradiance bake has no SH order: another one (a command's --sh-order) is no other
    # setting
    bake(vol, dataclasses.replace(config, samples=7, sh_order=3), out=path, workers=2)


def test_checkpoints_take_at_most_a_share_of_the_bake(monkeypatch, tmp_path):
    """`Checkpoints` saves once `seconds` have passed, then waits 1 / `SAVE_SHARE` times
    as long as a save took when that is longer (a clock the saves move by 10 s)."""
    import types

    from isolume.baking import saves as saves_module

    clock = [0.0]
    monkeypatch.setattr(saves_module, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))

    class Slow:
        def save(self, path):
            clock[0] += 10.0

    saves = saves_module.Checkpoints(Slow(), tmp_path / "l.npz", 60.0)
    wait = 10 / saves_module.SAVE_SHARE  # after the first save, which ends at 71 s
    for now, count in ((59.0, 0), (61.0, 1), (200.0, 1), (70 + wait, 1), (72 + wait, 2)):
        clock[0] = now
        saves(np.zeros(0))
        assert saves.saves == count, now
    fast = saves_module.Checkpoints(Slow(), None, 0.0)
    fast(np.zeros(0))
    assert fast.saves == 0  # no file: no saves


def test_a_checkpoint_that_cannot_be_written_ends_the_bake_without_trying_again(tmp_path):
    """A checkpoint's save that fails (`WriteError`: a full disk) is raised, and the commits
    the bake still makes as it stops do not try again (each try writes the whole file)."""
    from isolume.baking import saves as saves_module

    class Full:
        tries = 0

        def save(self, path):
            Full.tries += 1
            raise WriteError(f"{path}: cannot write the lattice: No space left on device")

    saves = saves_module.Checkpoints(Full(), tmp_path / "l.npz", 0.0)
    with pytest.raises(WriteError, match="No space left"):
        saves(np.zeros(0))
    saves(np.zeros(0))
    assert Full.tries == 1 and saves.saves == 0


def test_interrupt_keeps_finished_texels_and_resume_completes(tmp_path, monkeypatch):
    from isolume.baking.backend import ThreadBackend
    from isolume.baking.errors import BakeInterrupted

    config = BakeConfig(samples=20, bounces=1, env="constant:1,1,1", max_move=0.5)
    vol = make("shells", 32)
    whole = bake(vol, config, workers=2)
    assert len(whole.meta["plan"]["levels"]) > 6
    original = ThreadBackend._submit_level
    calls = {"n": 0}

    def interrupting(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 6:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(ThreadBackend, "_submit_level", interrupting)
    path = tmp_path / "cut.npz"
    with pytest.raises(BakeInterrupted) as stop:
        bake(vol, config, out=path, workers=2)
    assert _stored(path)  # saved quickly: the user is waiting
    cut = Lattice.load(path, vol)
    finished = cut.samples > 0
    assert 0 < finished.sum() < (whole.samples > 0).sum()
    assert stop.value.finished == finished.sum()  # told, not read from the file again
    assert (cut.samples[finished] == 20).all()  # only whole texels were kept
    np.testing.assert_allclose(cut.values[finished], whole.values[finished], rtol=1e-6)
    monkeypatch.setattr(ThreadBackend, "_submit_level", original)
    done = bake(vol, config, out=path, workers=2)
    np.testing.assert_allclose(done.values, whole.values, rtol=2e-6, atol=1e-6)
    assert not _stored(path)


def test_a_ctrl_c_out_of_a_kernels_loading_is_an_interrupt_too(tmp_path, monkeypatch):
    """A Ctrl-C that lands while numba loads a kernel comes out of the call as a
    SystemError whose context is the KeyboardInterrupt: the bake saves its finished
    texels and raises `BakeInterrupted` as for any Ctrl-C; another SystemError stays
    a bug and keeps its traceback."""
    from isolume.baking.backend import ThreadBackend
    from isolume.baking.errors import BakeInterrupted

    config = BakeConfig(samples=8, bounces=1, env="constant:1,1,1", max_move=0.5)
    vol = make("shells", 24)
    original = ThreadBackend._submit_level
    calls = {"n": 0}

    def failing(error, during_interrupt):
        def submit(self, *args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 4 and during_interrupt:
                try:
                    raise KeyboardInterrupt
                except KeyboardInterrupt:
                    raise error  # noqa: B904  (as numba does: the interrupt its context)
            if calls["n"] == 4:
                raise error
            return original(self, *args, **kwargs)
        return submit

    monkeypatch.setattr(ThreadBackend, "_submit_level", failing(SystemError(
        "CPUDispatcher returned a result with an exception set"), True))
    path = tmp_path / "cut.npz"
    with pytest.raises(BakeInterrupted) as stop:
        bake(vol, config, out=path, workers=2)
    assert stop.value.finished == np.count_nonzero(Lattice.load(path, vol).samples) > 0
    calls["n"] = 0
    monkeypatch.setattr(ThreadBackend, "_submit_level", failing(SystemError("plain"), False))
    with pytest.raises(SystemError, match="plain"):
        bake(vol, config, out=tmp_path / "bug.npz", workers=2)


def _stored(path) -> bool:
    """Whether the values of the lattice file `path` are stored, not deflated (a save
    made while a Ctrl-C waits: `lattice_file.quick_saves`)."""
    import zipfile

    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("values.npy")
    return info.compress_size >= info.file_size


def test_a_ctrl_c_while_the_finished_bake_saves_lets_the_save_end(tmp_path,
                                                                  ctrl_c_during_save):
    """One Ctrl-C during the final save: the file is written whole (the same lattice as a
    bake left alone; what was not deflated yet stored, the same bake run again deflates
    it), then KeyboardInterrupt; with `keep_interrupted` the lattice is returned. A
    second Ctrl-C abandons the save and leaves no file. Python's own SIGINT handler is
    back afterwards."""
    import signal

    config = BakeConfig(samples=4, bounces=1, env="constant:1,1,1", max_move=0.5)
    vol = make("shells", 24)
    alone = bake(vol, config, workers=2)
    ctrl_c_during_save(1)
    path = tmp_path / "once.npz"
    with pytest.raises(KeyboardInterrupt):
        bake(vol, config, out=path, workers=2)
    assert _stored(path)  # what was left to deflate at the press: stored, to end sooner
    saved = Lattice.load(path, vol)
    np.testing.assert_array_equal(saved.values, alone.values)
    np.testing.assert_array_equal(saved.samples, alone.samples)
    ctrl_c_during_save(0)
    again = bake(vol, config, out=path, workers=2)  # the same bake again deflates it
    assert not _stored(path)
    np.testing.assert_array_equal(again.values, alone.values)
    ctrl_c_during_save(1)
    kept = bake(vol, config, out=tmp_path / "kept.npz", workers=2, keep_interrupted=True)
    np.testing.assert_array_equal(kept.values, alone.values)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    ctrl_c_during_save(2)
    from isolume.baking.errors import SaveAbandoned

    with pytest.raises(SaveAbandoned):  # the command says the texels were not saved
        bake(vol, config, out=tmp_path / "twice.npz", workers=2)
    assert not (tmp_path / "twice.npz").exists()
    assert not list(tmp_path.glob(".twice.npz.*"))  # nor a temporary file
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_level_approximation_error_shrinks_with_more_levels():
    """Against each texel's exact isosurface (one mesh per texel), the level scheme's error
    falls as levels are added, down to the Monte Carlo noise of the comparison.

    The noise of (lattice - exact) is sqrt(2) standard errors per texel (independent
    estimates of equal variance); the finest scheme must come within 3x that.
    """
    from isolume.baking.bake import path_settings, tracing_lights
    from isolume.baking.integrator import trace_paths
    from isolume.baking.passes import start_points
    from isolume.baking.plan import make_plan
    from isolume.baking.rng import path_keys
    from isolume.baking.trace import Scene

    vol = make("shells", 40)
    samples = 128
    base = BakeConfig(samples=samples, bounces=1, env="constant:1,1,1", iso_range=(0.05, 0.95))
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    plan = make_plan(vol, geometry, base)
    rng = np.random.default_rng(5)
    pick = np.sort(rng.choice(len(plan.ids), 12, replace=False))
    exact, stderr = [], []
    lighting, settings = tracing_lights(base), path_settings(vol, base)
    for pos in pick:
        iso = float(plan.target[pos])
        mesh = volumes.isosurface(vol, iso)
        scene = Scene(mesh.vertices, mesh.faces)
        centre = geometry.centres(plan.ids[[pos]])
        origin, normal = start_points(vol, centre, iso, base, plan.high[[pos]])
        keys = path_keys(99, np.full(samples, plan.ids[pos]), np.arange(samples))
        est = trace_paths(scene, np.repeat(origin, samples, 0), np.repeat(normal, samples, 0),
                          keys, lighting, settings)[:, 0]
        exact.append(est.mean())
        stderr.append(est.std() / np.sqrt(samples))
    exact, stderr = np.array(exact), np.array(stderr)
    noise = np.sqrt(np.mean(2 * stderr**2)) / exact.mean()
    errors = []
    for levels in (2, 6, 48):
        config = dataclasses.replace(base, max_levels=levels, max_move=0.01)
        lattice = bake(vol, config, workers=2)
        got = lattice.values.reshape(-1, 3)[plan.ids[pick], 0]
        errors.append(np.sqrt(np.mean((got - exact) ** 2)) / exact.mean())
    assert errors[0] > errors[1] > errors[2]
    assert errors[0] > 3 * noise  # the coarse scheme's error is real, not noise
    assert errors[2] < 3 * noise


def test_lattice_file_refuses_another_volume(tmp_path):
    path = tmp_path / "s.npz"
    bake(make("sphere", 24), BakeConfig(samples=4, bounces=0), out=path)
    with pytest.raises(BakeError, match=r"baked for volume 'sphere'.*not for 'torus'"):
        Lattice.load(path, make("torus", 24))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(BakeError, match=r"junk\.npz: not a lattice file"):
        Lattice.load(tmp_path / "junk.npz")
    whole = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(whole[:len(whole) // 2])  # a copy cut short
    with pytest.raises(BakeError, match=r"cut\.npz: a truncated or damaged lattice file"):
        Lattice.load(tmp_path / "cut.npz")


def test_lattice_metadata(tmp_path):
    path = tmp_path / "s.npz"
    vol = make("sphere", 24)
    config = BakeConfig(samples=4, bounces=1)
    bake(vol, config, out=path)
    lattice = Lattice.load(path, vol)
    meta = lattice.meta
    assert meta["format_version"] == 2 and meta["kind"] == "irradiance"
    assert meta["volume"]["shape"] == [24, 24, 24] and meta["volume"]["hash"] == vol.data_hash()
    assert lattice.config == config and "config" not in meta
    assert meta["rays_traced"] > 0 and meta["trace_seconds"] > 0
    assert lattice.values.shape == (24, 24, 24, 3) and lattice.samples.dtype == np.uint32
    assert not list(tmp_path.glob("*.tmp"))  # atomic write left no temporary


def test_lattice_sample_is_trilinear_at_texel_centres():
    vol = make("sphere", 16)
    geometry = LatticeGeometry.for_volume(vol, 0.5)
    assert geometry.shape == (8, 8, 8)
    values = np.random.default_rng(1).random((*geometry.shape, 3)).astype(np.float32)
    lattice = Lattice(geometry, values, np.ones(geometry.shape, np.uint32),
                      np.zeros(geometry.shape, np.float32), np.ones(geometry.shape, bool))
    ids = np.array([0, 9, 100, 511])
    np.testing.assert_allclose(lattice.sample(geometry.centres(ids)),
                               values.reshape(-1, 3)[ids], rtol=1e-6)
    a, b = geometry.centres(np.array([9])), geometry.centres(np.array([10]))
    mid = lattice.sample(0.5 * (a + b))
    np.testing.assert_allclose(mid[0], 0.5 * (values.reshape(-1, 3)[9] + values.reshape(-1, 3)[10]),
                               rtol=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"lights": ("spot:1,2,3:1,1,1",)}, "expected point"),
        ({"lights": ("dir:0,0,0:1,1,1",)}, "direction must not be zero"),
        ({"mode": "sh", "lights": ("dir:0,0,1:1,1,1",)}, "not low-frequency"),
        ({"env": "", "lights": ()}, "nothing lights"),
        ({"albedo": (1.5, 0.5, 0.5)}, r"\[0, 1\]"),
        ({"samples": 0}, "at least 1"),
        ({"samples": 2, "target_error": 0.1}, "at least 4"),
        ({"target_error": 1.5}, "between 0 and 1"),
    ],
)
def test_bad_bake_config(kwargs, match):
    with pytest.raises(BakeError, match=match):
        BakeConfig(**kwargs)


def test_iso_range_outside_data():
    with pytest.raises(BakeError, match="does not overlap the data range"):
        bake(make("sphere", 16), BakeConfig(samples=1, iso_range=(2.0, 3.0)))


def test_sphere_radius_constant_is_what_the_volume_uses():
    assert SPHERE_RADIUS == pytest.approx(0.35)


def test_a_pass_counts_its_samples_in_two_bytes_where_they_fit():
    """`Baker.pending` keeps no per-texel counts where every texel of the plan has the
    same samples done and to do (a whole bake from scratch), else the samples done and to
    do of the busy texels only (a round of a noise target on one level group allocates
    nothing over the whole plan), in uint16 while done + to do fits and in int32 past
    that, with the same counts and busy texels either way; the busy texels are grouped
    by lower level when asked."""
    from isolume.baking.bake import Baker

    baker = Baker(make("sphere", 12), BakeConfig(samples=3, bounces=0), workers=1)
    try:
        count = len(baker.plan.ids)
        alike = baker.pending(None, None)
        assert alike.done.shape == () and alike.busy is None
        done, remaining = alike.counts(np.arange(count))
        assert done.dtype == np.uint16 and remaining.dtype == np.uint16
        assert (done == 0).all() and (remaining == 3).all()
        small = baker.pending(np.arange(count), 3)
        assert small.done.dtype == np.uint16 and small.remaining.dtype == np.uint16
        assert (small.done == 0).all() and (small.remaining == 3).all()
        levels = range(alike.first, alike.last + 1)
        for work in (alike, small):
            grouped = np.concatenate([work.lower_on(level) for level in levels])
            np.testing.assert_array_equal(np.sort(grouped), np.arange(count))
            for level in levels:
                assert (baker.plan.lower[work.lower_on(level)] == level).all()
        positions = np.arange(0, count, 2)
        wide = baker.pending(positions, np.full(len(positions), 70_000))
        assert wide.done.dtype == np.int32 and wide.remaining.dtype == np.int32
        assert wide.done.shape == wide.remaining.shape == (len(positions),)
        done, remaining = wide.counts(positions[::-3])
        assert (done == 0).all() and (remaining == 70_000).all()
        np.testing.assert_array_equal(wide.busy, positions)
        some = baker.pending(np.arange(count), np.arange(count) % 4)  # texel 4k needs none
        np.testing.assert_array_equal(some.busy, np.flatnonzero(np.arange(count) % 4))
        np.testing.assert_array_equal(some.counts(some.busy[::-1])[1],
                                      (some.busy % 4)[::-1])
        busy = np.concatenate([wide.lower_on(level)
                               for level in range(wide.first, wide.last + 1)])
        np.testing.assert_array_equal(np.sort(busy), positions)
    finally:
        baker.close()


def test_sorted_unique_matches_numpy_unique():
    """`bake.sorted_unique` gives `numpy.unique`'s answer, rising input or not."""
    from isolume.baking.bake import sorted_unique

    rng = np.random.default_rng(5)
    for values in (rng.integers(0, 50, 200), np.arange(7), np.array([3]), np.array([], int),
                   np.array([1, 2, 2, 3])):
        np.testing.assert_array_equal(sorted_unique(values), np.unique(values))
