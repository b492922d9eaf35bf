"""`baking.plan`: targets clamped to the iso range, levels inside it, level counts that
follow the samples and the scenes' cost, and Newton moves that reach the level."""

import dataclasses

import numpy as np
import pytest

from isolume import volumes
from isolume.baking import BakeConfig, bake
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.plan import (
    MOVE_LIMITS,
    SCENE_SHARE,
    UNLANDED,
    landed_points,
    level_budget,
    make_plan,
    move_limit,
    project_to_level,
)
from isolume.volumes import Volume
from isolume.volumes.synthetic import make


def _plan(vol, **kwargs):
    config = BakeConfig(**kwargs)
    return make_plan(vol, LatticeGeometry.for_volume(vol, config.scale), config), config


def test_targets_are_the_middle_of_the_isovalues_that_read_a_texel():
    """`lit_isovalues`: a texel whose neighbourhood holds only isovalues of the range is lit
    at its own value; one near an end, at the middle of the isovalues in reach inside the
    range; one beyond the range that a surface of the range reaches, at the middle of
    those; one that none reaches, at the nearer end."""
    from isolume.baking.plan import lit_isovalues

    rho = np.array([0.5, 0.42, 0.3, 0.9, 0.45])
    span = np.array([0.05, 0.05, 0.2, 0.1, 1.0])
    np.testing.assert_allclose(lit_isovalues(rho, span, 0.4, 0.6),
                               [0.5, 0.435, 0.45, 0.6, 0.5])
    vol = make("shells", 32)
    plan, _ = _plan(vol, samples=64, iso_range=(0.4, 0.6))
    lo, hi = plan.iso_range
    assert (lo, hi) == (0.4, 0.6)
    assert plan.rho.min() < lo and plan.rho.max() > hi  # corners of crossing cells reach out
    assert plan.target.min() >= np.float32(lo) and plan.target.max() <= np.float32(hi)
    assert plan.levels[0] >= lo and plan.levels[-1] <= hi
    assert np.all(np.diff(plan.levels) > 0)


def test_automatic_levels_follow_the_samples():
    """The move limit scales as sqrt(256 / N) within its bounds; more samples, more levels."""
    assert move_limit(BakeConfig(samples=256)) == pytest.approx(0.5)
    assert move_limit(BakeConfig(samples=64)) == pytest.approx(1.0)
    assert move_limit(BakeConfig(samples=4)) == MOVE_LIMITS[1]
    assert move_limit(BakeConfig(samples=4096)) == MOVE_LIMITS[0]
    assert move_limit(BakeConfig(samples=4, max_move=0.3)) == 0.3  # explicit: as told
    vol = make("shells", 40)
    counts = [len(_plan(vol, samples=n, iso_range=(0.1, 0.9))[0].levels) for n in (4, 64, 4096)]
    assert counts[0] < counts[1] < counts[2]


def test_noise_free_bakes_keep_fine_levels():
    """Directional light only, no bounces: every path gives the same estimate, so neither
    the samples nor the scenes' cost may coarsen the levels."""
    vol = make("shells", 40)
    lights = ("dir:0,0,1:1,1,1",)
    quick, _ = _plan(vol, samples=2, bounces=0, env="", lights=lights, iso_range=(0.1, 0.9))
    noisy, _ = _plan(vol, samples=2, bounces=0, iso_range=(0.1, 0.9))
    assert quick.move_limit == 0.5 and len(quick.levels) > 2 * len(noisy.levels)


def test_level_budget_keeps_scenes_a_fraction_of_the_tracing():
    """A quick bake (few paths) gets few levels; a long one is not capped by the cost."""
    vol = make("engine", 64)
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    quick = BakeConfig(samples=4, bounces=0, iso_range=(0.2, 0.4))
    long = dataclasses.replace(quick, samples=1024, bounces=2)
    plan, _ = _plan(vol, **dataclasses.asdict(quick))
    # no surface crossed: the volume's cost only
    budget_quick = level_budget(vol, geometry, quick, 0, len(plan.ids))
    budget_long = level_budget(vol, geometry, long, 0, len(plan.ids))
    rays = len(plan.ids) * 4
    assert budget_quick == max(2, int(SCENE_SHARE * rays / (0.06 * vol.data.size)))
    assert budget_long == long.max_levels
    assert len(plan.levels) <= budget_quick


def test_resumed_bake_keeps_the_levels_its_samples_were_traced_on(tmp_path):
    vol = make("shells", 32)
    config = BakeConfig(samples=8, bounces=1, iso_range=(0.1, 0.7))
    path = tmp_path / "l.npz"
    first = bake(vol, config, out=path, workers=2)
    more = dataclasses.replace(config, samples=512)
    fresh, _ = _plan(vol, **dataclasses.asdict(more))
    resumed = bake(vol, dataclasses.replace(more, samples=24), out=path, workers=2)
    assert len(fresh.levels) != len(first.meta["plan"]["levels"])
    assert resumed.meta["plan"]["levels"] == first.meta["plan"]["levels"]
    assert resumed.meta["plan"]["iso_range"] == [0.1, 0.7]


def test_damped_newton_walks_out_of_a_plateau_onto_the_level():
    """A point deep in the flat part of a tanh profile (gradient e^-4 of the edge's): one
    undamped Newton step would overshoot by tens of voxels; damped steps of at most a
    voxel reach the level within the allowed move."""
    size, w = 48, 1.2
    z = np.arange(size, dtype=np.float32)
    data = 0.5 - 0.5 * np.tanh((z - 24) / w)
    vol = Volume(np.broadcast_to(data[:, None, None], (size, 8, 8)).copy(), (1, 1, 1),
                 (0, 0, 0), name="edge", source="edge")
    start = np.array([[4.0, 4.0, 20.5]])  # 3.5 voxels inside, value 0.9975
    moved = project_to_level(vol, start, 0.5, max_move=6.0)
    assert volumes.value_at(vol, moved)[0] == pytest.approx(0.5, abs=1e-3)
    assert moved[0, 2] == pytest.approx(24.0, abs=0.05)
    stuck = project_to_level(vol, start, 0.5, max_move=2.0)  # too far: clamped, not past
    assert np.linalg.norm(stuck - start) == pytest.approx(2.0)


def test_render_refuses_isovalues_outside_the_baked_range(tmp_path, capsys):
    """A lattice lights its texels on surfaces inside its iso range: at another isovalue
    the picture would be wrong, so ``render`` says so (exit 2, one line) instead."""
    from isolume.app.cli import main

    path = tmp_path / "l.npz"
    bake(make("sphere", 24), BakeConfig(samples=2, bounces=0, iso_range=(0.4, 0.6)),
         out=path, workers=2)
    common = ["render", "synthetic:sphere:24", "--lattice", str(path), "--size", "24x24",
              "--gl", "osmesa", "--out", str(tmp_path / "a.png")]
    assert main([*common, "--iso", "0.5"]) == 0
    capsys.readouterr()
    assert main([*common, "--iso", "0.2"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"{path}: baked for isovalues 0.4 to 0.6; at isovalue 0.2" in err
    assert "--iso-range" in err


def test_viewer_panel_warns_outside_the_baked_range():
    from isolume.app.viewer.bake_client import range_warning

    meta = {"plan": {"iso_range": [0.4, 0.6]}}
    assert range_warning(meta, 0.5) == ()
    assert "outside the baked range 0.4 to 0.6" in range_warning(meta, 0.7)[0]
    assert range_warning({"plan": {}}, 0.9) == ()  # older files serve every isovalue


@pytest.mark.parametrize("spec, scale", [("synthetic:engine:48", 1.0),
                                         ("synthetic:engine:48", 0.7),
                                         ("synthetic:torus:33", 1.6)])
def test_separable_texel_values_equal_trilinear_lookups(spec, scale):
    from isolume.baking.plan import texel_values

    vol = volumes.load(spec)
    geometry = LatticeGeometry.for_volume(vol, scale)
    want = volumes.value_at(vol, geometry.all_centres().reshape(-1, 3))
    np.testing.assert_array_equal(texel_values(vol, geometry),
                                  want.reshape(geometry.shape).astype(np.float32))


@pytest.mark.parametrize("threads", [1, 3])
def test_active_texels_are_flatnonzero_and_their_values(threads):
    """The active texels' ids, counted and gathered by z-slabs on several threads, are
    ``numpy.flatnonzero`` in its index type, and their values those of the grid — empty
    layers, an empty mask and a full one included."""
    from isolume.baking.plan import active_texels, index_type
    from isolume.volumes import cores

    gen = np.random.default_rng(5)
    masks = [gen.random((37, 20, 11)) < 0.3, np.zeros((4, 3, 2), bool), np.ones((3, 1, 5), bool)]
    masks[0][5:9] = False
    cores.use(threads)
    try:
        for active in masks:
            rho = gen.normal(size=active.shape).astype(np.float32)
            ids, values = active_texels(active, rho)
            want = np.flatnonzero(active).astype(index_type(active.size))
            assert ids.dtype == want.dtype and values.dtype == np.float32
            np.testing.assert_array_equal(ids, want)
            np.testing.assert_array_equal(values, rho.reshape(-1)[want])
    finally:
        cores.use(None)


def test_binned_percentiles_equal_numpy_per_bin():
    from isolume.baking.plan import _binned_percentile

    gen = np.random.default_rng(1)
    which, values = gen.integers(0, 50, 5000), gen.normal(size=5000)
    which[which == 7] = 8  # an empty bin
    got = _binned_percentile(which, values, 50, 10, -1.0)
    want = [np.percentile(values[which == k], 10) if (which == k).any() else -1.0
            for k in range(50)]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("threads", [1, 3])
def test_values_grouped_by_bin_in_blocks_are_a_stable_sort(threads):
    """The counting sort of the level choice, in blocks on several threads, is
    ``values[argsort(which, stable)]`` to the bit, with numpy's bin counts — ties, empty
    bins, one bin holding most values and blocks of 1024 included; and, as the nearest
    points group corners, the indices grouped by the top bits of their keys."""
    from isolume.baking.plan import grouped_by_bin
    from isolume.volumes import cores

    gen = np.random.default_rng(3)
    which = np.minimum(gen.exponential(30, 70_000), 511).astype(np.uint16)
    which[:40_000] = 9
    values = np.round(gen.gamma(2, 1, len(which)), 1).astype(np.float32)
    cores.use(threads)
    try:
        ranked, counts = grouped_by_bin(which, values, 512)
    finally:
        cores.use(None)
    np.testing.assert_array_equal(ranked, values[np.argsort(which, kind="stable")])
    np.testing.assert_array_equal(counts, np.bincount(which, minlength=512))
    ids = gen.integers(0, 1 << 20, 90_000)  # texel ids, binned by their top bits, indices
    cores.use(threads)
    try:
        order, counts = grouped_by_bin(ids, None, 1 << 7, shift=13)
    finally:
        cores.use(None)
    np.testing.assert_array_equal(order, np.argsort(ids >> 13, kind="stable"))
    np.testing.assert_array_equal(counts, np.bincount(ids >> 13, minlength=1 << 7))


def test_bake_command_records_levels_and_takes_max_move(tmp_path, capsys):
    from isolume.app.cli import main
    from isolume.baking import Lattice

    out = tmp_path / "l.npz"
    argv = ["bake", "synthetic:shells:24", "--out", str(out), "--samples", "4",
            "--bounces", "0", "--env", "constant:1,1,1", "--iso-range", "0.3", "0.6"]
    assert main([*argv, "--max-move", "0.25"]) == 0
    assert "planning: paths onto" in capsys.readouterr().err  # the plan's stages shown
    fine = Lattice.load(out, volumes.load("synthetic:shells:24")).meta["plan"]
    assert fine["move_limit_voxels"] == 0.25 and fine["iso_range"] == [0.3, 0.6]
    out.unlink()
    assert main(argv) == 0
    auto = Lattice.load(out, volumes.load("synthetic:shells:24")).meta["plan"]
    assert auto["move_limit_voxels"] == 2.0 and len(auto["levels"]) < len(fine["levels"])
    capsys.readouterr()
    assert main([*argv, "--max-move", "9"]) == 2
    assert "--max-move 9: expected (0, 4] voxels" in capsys.readouterr().err


def test_stalled_newton_falls_back_to_the_nearest_crossing_along_neighbour_lines():
    """A segmented (binary) volume: 3 voxels from the step the smoothed gradient is exactly
    zero, so Newton cannot move; the point is then taken to the nearest place where the
    trilinear field crosses the level along the 26 neighbour directions — the step face,
    3 voxels straight down, exactly on the level."""
    data = np.zeros((16, 8, 8), np.float32)
    data[:8] = 1.0  # material below z = 7.5
    vol = Volume(data, (1, 1, 1), (0, 0, 0), name="step", source="step")
    start = np.array([[3.5, 3.5, 10.5]])
    assert np.linalg.norm(volumes.gradient_at(vol, start)) == 0.0
    moved = project_to_level(vol, start, 0.5, max_move=4.0)
    np.testing.assert_allclose(moved, [[3.5, 3.5, 7.5]], atol=1e-5)
    far = project_to_level(vol, start, 0.5, max_move=2.0)  # out of reach: left where it was
    np.testing.assert_array_equal(far, start)


def test_levels_start_where_the_plan_landed_their_texels():
    """The plan's reach test projects every texel onto the levels it uses; laying out a
    level reuses those points (`Plan.landing`, in one compiled call:
    `plan_kernels.landed_starts`) and gets the start points of the array code
    (`start_points` from the landed points) and of a fresh projection (rounded as the
    plan keeps them), to the bit, a chunk at a time as for the whole level."""
    from isolume.baking.passes import lay_out_level, start_points
    from isolume.baking.plan import landed_points, newton_reach

    vol = make("mixing_layer", 32)
    plan, config = _plan(vol, samples=8, bounces=0, iso_range=(0.2, 0.7), max_move=0.5)
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    uses = np.stack([plan.weight < 1, plan.weight > 0], axis=1)
    assert (plan.landing[uses] != UNLANDED).all()
    level = 1
    here = np.flatnonzero(plan.lower == level)
    below = np.flatnonzero(plan.lower == level - 1)
    assert len(here) and len(below) and (plan.weight[below] > 0).any()
    done = np.zeros(len(plan.ids), np.int64)
    remaining = np.full(len(plan.ids), 8, np.int64)
    args = (vol, geometry, config, float(plan.levels[level]), plan.ids, plan.phase,
            plan.weight, plan.high, here, below, done, remaining)
    paths, starts = lay_out_level(*args, plan.landing)
    reused = starts.of(0, len(paths.texels))
    _, fresh = lay_out_level(*args)
    fresh = fresh.of(0, len(paths.texels))
    np.testing.assert_array_equal(reused.origins, fresh.origins)
    np.testing.assert_array_equal(reused.normals, fresh.normals)
    centres = geometry.centres(plan.ids[paths.texels])
    landed = landed_points(plan.landing[paths.texels, paths.upper.astype(np.int64)], centres,
                           newton_reach(vol, config))
    origins, normals = start_points(vol, centres, float(plan.levels[level]), config,
                                    plan.high[paths.texels], landed)
    np.testing.assert_array_equal(reused.origins, origins.astype(np.float32))
    np.testing.assert_array_equal(reused.normals, normals.astype(np.float32))
    assert paths.upper.any() and not paths.upper.all() and 0 < plan.high.mean() < 1
    cut = len(paths.texels) // 3  # a chunk's start points: those of the whole level's
    part = starts.of(cut, len(paths.texels))
    np.testing.assert_array_equal(part.origins, reused.origins[cut:])
    np.testing.assert_array_equal(part.normals, reused.normals[cut:])
    origins, _ = start_points(vol, geometry.centres(plan.ids[paths.texels]),
                              float(plan.levels[level]), config, plan.high[paths.texels])
    np.testing.assert_array_equal(fresh.origins, origins.astype(np.float32))


def test_selected_cells_equal_numpy_reductions_and_dilation():
    """`select_cells` against the plain numpy recipe: corner minima and maxima by eight
    shifted views, the cell mask, its corners by eight shifted ORs."""
    from isolume.baking.plan import select_cells

    rho = np.random.default_rng(3).normal(size=(7, 5, 9)).astype(np.float32)
    views = [rho[a:a + 6, b:b + 4, c:c + 8] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    cmin, cmax = np.minimum.reduce(views), np.maximum.reduce(views)
    lo, hi, min_span, mid = 1.0, 1.6, 2.8, 1.3
    cells = (cmax >= lo) & (cmin <= hi) & (cmax - cmin > min_span)
    want = np.zeros(rho.shape, bool)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                want[a:a + 6, b:b + 4, c:c + 8] |= cells
    active, crossed = select_cells(rho, lo, hi, min_span, mid)
    np.testing.assert_array_equal(active, want)
    assert crossed == np.count_nonzero(cells & (cmin <= mid) & (cmax >= mid))
    assert 0 < crossed < np.count_nonzero(cells) and 0 < active.sum() < active.size


def _starts_inside(vol: Volume, plan, config) -> np.ndarray:
    """(T,) bool: does some level a texel uses start its paths on the high side of it?"""
    h = float(np.mean(vol.spacing))
    centres = LatticeGeometry.for_volume(vol, config.scale).centres(plan.ids)
    inside = np.zeros(len(plan.ids), bool)
    for side, used in ((0, plan.weight < 1), (1, plan.weight > 0)):
        level = plan.levels[plan.lower + side][used]
        landed = landed_points(plan.landing[used, side], centres[used], plan.reach)
        start = landed + config.offset * h * volumes.normals_at(vol, landed)
        inside[used] |= volumes.value_at(vol, start) >= level
    return inside


def test_paths_start_outside_the_thin_shell_of_a_fin_below_the_isovalue(monkeypatch):
    """The synthetic engine's cooling fins peak near 0.29, just below its isovalue 0.3.
    Texels by a fin's root carry values near that peak; the level of such a value is a
    thin shell around the fin's crest, the smoothed normal there is the casing's, and a
    start point moved along it lands inside the shell (every path blocked: black texels,
    a dark streak on the casing). The plan moves their paths to the bracketing level
    whose start lies outside; only texels that can use neither are left (counted as
    unreachable)."""
    from isolume.baking import plan as plan_module

    vol = make("engine", 48)
    plan, config = _plan(vol, samples=4, bounces=0, iso_range=(0.2, 0.5), max_move=0.5)
    inside = _starts_inside(vol, plan, config).sum()
    assert inside <= plan.unreachable
    monkeypatch.setattr(plan_module, "start_lift", lambda volume, config: 0.0)  # unchecked
    unchecked, _ = _plan(vol, samples=4, bounces=0, iso_range=(0.2, 0.5), max_move=0.5)
    assert _starts_inside(vol, unchecked, config).sum() >= max(50, 5 * inside)


def test_plan_is_the_same_whatever_its_block_size(monkeypatch):
    """The plan works on its texels block by block (`PLAN_BLOCK`, bounding its
    temporaries); every array of the plan is the same bits with blocks of 997 texels as
    with one block."""
    from isolume.baking import plan as plan_module

    vol = make("engine", 40)
    whole, _ = _plan(vol, samples=8, bounces=0)
    assert len(whole.ids) > 3 * 997
    monkeypatch.setattr(plan_module, "PLAN_BLOCK", 997)
    blocked, _ = _plan(vol, samples=8, bounces=0)
    for field in dataclasses.fields(whole):
        a, b = getattr(whole, field.name), getattr(blocked, field.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=field.name)
        else:
            assert a == b, field.name


def test_newton_steps_reuse_a_cells_gradients_to_the_bit():
    """Newton steps that stay in one lattice cell of the volume reuse its corner gradients
    (`volumes.field.newton_steps`): the landing points equal, to the bit, steps that read the
    eight corner gradients afresh every time (the compiled lookups, step for step),
    on points of the Marschner–Lobb function that converge or are clamped."""
    from isolume.volumes import field

    vol = make("marschner_lobb", 24)
    level, reach, iterations = 0.5, 2.5 * vol.spacing[0], 4
    surface = volumes.isosurface(vol, level).vertices[::23].astype(np.float64)
    rng = np.random.default_rng(5)  # up to two voxels off the surface: steps, some clamped
    points = surface + rng.uniform(-2, 2, surface.shape) * vol.spacing[0]
    moved = project_to_level(vol, points, level, max_move=reach, iterations=iterations)
    data, samples = vol.data[..., None], vol.data
    w, inverse = field._BSPLINE, 0.5 / np.asarray(vol.spacing, np.float64)
    origin, spacing = np.asarray(vol.origin, np.float64), np.asarray(vol.spacing, np.float64)
    value, g, corners = np.empty(1), np.empty(3), np.empty((8, 3), np.float32)
    window = np.empty((4, 4, 4), np.float32)
    voxel = float(spacing.min())
    compared = 0
    for i, (sx, sy, sz) in enumerate(points):
        px, py, pz = sx, sy, sz
        for _ in range(iterations + int(reach / voxel)):
            zi, yi, xi = ((pz - origin[2]) / spacing[2], (py - origin[1]) / spacing[1],
                          (px - origin[0]) / spacing[0])
            field._lerp3(data, zi, yi, xi, value)  # compiled, corners read afresh
            field.gradient_lerp(samples, w, inverse, zi, yi, xi, corners, window, g)
            g2 = max(g[0] * g[0] + g[1] * g[1] + g[2] * g[2], 1e-30)
            step = (level - value[0]) / g2
            length = abs(step) * np.sqrt(g2)
            if length > voxel:
                step *= voxel / length
            qx, qy, qz = px + step * g[0], py + step * g[1], pz + step * g[2]
            dx, dy, dz = qx - sx, qy - sy, qz - sz
            dist = np.sqrt(dx * dx + dy * dy + dz * dz)
            if dist > reach:
                qx, qy, qz = sx + dx * (reach / dist), sy + dy * (reach / dist), sz + dz * (
                    reach / dist)
            done = abs(qx - px) + abs(qy - py) + abs(qz - pz) < 1e-4 * voxel
            px, py, pz = qx, qy, qz
            if done:
                break
        start = field.value_at_world(data, origin, spacing, sx, sy, sz, value) - level
        end = field.value_at_world(data, origin, spacing, px, py, pz, value) - level
        if abs(end) > field.STALLED_FRACTION * abs(start):
            continue  # the line search, not the steps: `test_stalled_newton_...`
        np.testing.assert_array_equal(moved[i], [px, py, pz], err_msg=f"point {i}")
        compared += 1
    assert compared >= 0.6 * len(points)


def test_a_bakes_plan_keeps_a_byte_for_the_level_and_no_box_mask():
    """What a bake holds per texel: the lower level's index in the smallest type that holds
    every level (uint8 up to 256 levels), and a traced plan (`Plan.traced_only`) without
    the replanning arrays or the box's mask — the Baker of `bake()` holds that one, and
    makes it without them."""
    from isolume.baking.bake import Baker

    vol = make("engine", 32)
    plan, config = _plan(vol, samples=4, bounces=0)
    assert plan.lower.dtype == np.uint8 and plan.lower.max() == len(plan.levels) - 2
    traced = plan.traced_only()
    assert traced.rho is None and traced.target is None and traced.active is None
    np.testing.assert_array_equal(traced.ids, np.flatnonzero(plan.active))
    many, _ = _plan(vol, samples=4, bounces=0, max_move=0.001, max_levels=300)
    assert len(many.levels) > 256 and many.lower.dtype == np.uint16
    made = make_plan(vol, LatticeGeometry.for_volume(vol, config.scale), config,
                     traced_only=True)  # let go of them while it is made: the same plan
    for field in dataclasses.fields(made):
        np.testing.assert_equal(getattr(made, field.name), getattr(traced, field.name),
                                err_msg=field.name)
    baker = Baker(vol, config, workers=1, packed=True)
    try:
        assert baker.plan.active is None and baker.plan.rho is None
    finally:
        baker.close()


def test_landing_offsets_keep_points_to_a_step_of_the_reach():
    """`Plan.landing` keeps a landing point in 6 bytes: every point within the reach comes
    back within half a step (reach / `LANDING_STEPS` / 2) per axis, a point decoded and
    encoded again is the same code (so whoever projects a texel gets the same start
    point), and a level not used (NaN) comes back NaN."""
    from isolume.baking.plan import landing_offsets, rounded_landing
    from isolume.baking.plan_kernels import LANDING_STEPS

    rng = np.random.default_rng(5)
    reach = 3.2
    centres = rng.uniform(0, 64, (20_000, 3))
    moves = rng.normal(size=(20_000, 3))
    moves *= reach * rng.uniform(0, 1, (20_000, 1)) / np.linalg.norm(moves, axis=1)[:, None]
    moves[:4] = [[reach, 0, 0], [0, -reach, 0], [0, 0, 0], [np.nan] * 3]
    codes = landing_offsets(centres + moves, centres, reach)
    assert codes.dtype == np.int16 and (codes[3] == UNLANDED).all()
    back = landed_points(codes, centres, reach)
    assert np.isnan(back[3]).all() and not np.isnan(np.delete(back, 3, axis=0)).any()
    error = np.abs(np.delete(back - centres - moves, 3, axis=0))
    assert error.max() <= 0.5 * reach / LANDING_STEPS * (1 + 1e-6)
    np.testing.assert_array_equal(landing_offsets(back, centres, reach), codes)
    np.testing.assert_array_equal(rounded_landing(back, centres, reach), back)


def test_flat_ids_in_four_bytes_bake_the_same_lattice_as_in_eight(monkeypatch):
    """A plan keeps its texels' flat ids in int32 while the box has fewer than 2³¹ texels
    (int64 past that); a bake with them is the same lattice to the bit as one with int64
    ids (the compiled kernels read int64 ids chunk by chunk)."""
    from isolume.baking import plan as plan_module

    assert plan_module.index_type(2**31 - 1) is np.int32
    assert plan_module.index_type(2**31) is np.int64
    vol = make("engine", 24)
    config = BakeConfig(samples=4, bounces=1, seed=3)
    narrow = bake(vol, config, workers=2, progress=False)
    monkeypatch.setattr(plan_module, "index_type", lambda texels: np.int64)
    wide = bake(vol, config, workers=2, progress=False)
    assert _plan(vol, samples=4)[0].ids.dtype == np.int64
    monkeypatch.undo()
    assert _plan(vol, samples=4)[0].ids.dtype == np.int32
    for name in ("values", "samples", "second", "facing"):
        np.testing.assert_array_equal(getattr(narrow, name), getattr(wide, name))
    assert narrow.samples.sum() > 0


def test_the_plan_tells_how_far_its_long_stages_have_come(monkeypatch):
    """`make_plan` tells each stage as it starts and, for the Newton steps, the side
    probes and the reach tests, the fraction done after each block: rising, ending at 1."""
    from isolume.baking import plan as plan_module
    from isolume.baking import sides

    monkeypatch.setattr(plan_module, "PLAN_BLOCK", 997)
    monkeypatch.setattr(sides, "TEXELS_PER_BATCH", 997)
    vol = make("engine", 40)
    config = BakeConfig(samples=8, bounces=0)
    told = []
    plan = make_plan(vol, LatticeGeometry.for_volume(vol, config.scale), config,
                     progress=lambda *said: told.append(said))
    started = [said[0] for said in told if len(said) == 1]
    levels = len(plan.levels)
    assert started == ["texel values", "gradients", f"paths onto {levels} levels",
                       f"seen sides on {levels} levels", "reach tests"]
    for stage in started[2:]:
        fractions = [said[1] for said in told if len(said) == 2 and said[0] == stage]
        assert len(fractions) >= 3, stage
        assert np.all(np.diff(fractions) > 0) and fractions[-1] == 1.0, (stage, fractions)
        first = next(i for i, said in enumerate(told) if said == (stage,))
        assert all(i > first for i, said in enumerate(told) if said[0] == stage
                   and len(said) == 2), stage


def _reference_reaches(volume, config, points, levels, reach, tol, high, landed):
    """The reach tests in arrays (`volumes.value_at`, `values_along_normals`,
    `project_to_level`), as independent of `plan_kernels.reach_tests` as numpy makes
    them: (N,) ok, (N,) moved, and `landed` (N, 3) filled where NaN."""
    from isolume.baking.plan import project_to_level, rounded_landing

    todo = np.isnan(landed[:, 0])
    landed[todo] = rounded_landing(project_to_level(volume, points[todo], levels[todo],
                                                    max_move=reach), points[todo], reach)
    ok = np.abs(volumes.value_at(volume, landed) - levels) <= tol
    if config.offset > 0:
        h = float(np.mean(volume.spacing))
        for flip in (False, True):
            these = high == flip
            beyond = volumes.values_along_normals(
                volume, landed[these], config.offset * h, smooth=config.normals == "smooth",
                flip=flip) - levels[these]
            ok[these] &= beyond > 0 if flip else beyond < 0
    return ok, np.linalg.norm(landed - points, axis=1).astype(np.float32), landed


@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
@pytest.mark.parametrize("normals", ["smooth", "gradient"])
def test_compiled_reach_tests_are_the_arrays_tests_to_the_bit(dtype, normals):
    """`plan_kernels.reach_tests` (one compiled call a block) against the same tests in
    arrays: for texels with and without a landing yet, on either side, lit on either
    side, the same ok flags, move lengths and landings, to the bit; the texels not asked
    about keep what they had."""
    from isolume.baking.plan import (
        UNLANDED,
        _Reaches,
        landed_points,
        landing_offsets,
        newton_reach,
        start_lift,
    )

    rng = np.random.default_rng(4)
    data = make("engine", 40).data
    vol = Volume((data * (200.0 if dtype == np.uint8 else 1.0)).astype(dtype),
                 spacing=(1.0, 1.2, 0.9), origin=(0.5, -1.0, 2.0))
    scale = 200.0 if dtype == np.uint8 else 1.0
    config = BakeConfig(samples=4, bounces=0, max_move=0.5, normals=normals)
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    ids = np.sort(rng.choice(int(np.prod(geometry.shape)), 4000, replace=False))
    levels = np.array([0.2, 0.3, 0.45]) * scale
    lower = rng.integers(0, 2, len(ids))
    high = rng.random(len(ids)) < 0.3
    reach = newton_reach(vol, config)
    centres = geometry.centres(ids)
    landing = np.full((len(ids), 3), UNLANDED, np.int16)
    landed_before = rng.random(len(ids)) < 0.5  # projected by an earlier test
    landing[landed_before] = landing_offsets(
        centres[landed_before] + rng.normal(0, 0.3 * reach, (landed_before.sum(), 3)),
        centres[landed_before], reach)
    which = rng.random(len(ids)) < 0.8
    ok0 = rng.random(len(ids)) < 0.5
    moved0 = rng.random(len(ids)).astype(np.float32)
    lift = start_lift(vol, config)
    assert lift > 0
    tests = _Reaches(vol, config, geometry, ids, reach, lift, levels, lower, high)
    for side in (0, 1):
        got_landing = landing.copy()
        ok, moved = tests(side, which, got_landing, ok0, moved0)
        landed = landed_points(landing[which], centres[which], reach)
        tol = 0.1 * (levels[lower[which] + 1] - levels[lower[which]])
        want_ok, want_moved, want_landed = _reference_reaches(
            vol, config, centres[which], levels[lower[which] + side], reach, tol,
            high[which], landed)
        np.testing.assert_array_equal(ok[which], want_ok)
        np.testing.assert_array_equal(moved[which], want_moved)
        np.testing.assert_array_equal(got_landing[which],
                                      landing_offsets(want_landed, centres[which], reach))
        np.testing.assert_array_equal(ok[~which], ok0[~which])
        np.testing.assert_array_equal(moved[~which], moved0[~which])
        np.testing.assert_array_equal(got_landing[~which], landing[~which])
        assert 0.2 < want_ok.mean() < 0.95


@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
def test_compiled_gradient_norms_are_numpys_to_the_bit(dtype):
    """`plan._gradients` (`plan_kernels.gradient_norms`, one compiled call a block)
    against ``np.linalg.norm(volumes.gradient_at(volume, centres), axis=1) * h`` — float32
    gradients, their float32 length times h in float32 — on a volume with its own origin
    and spacing, over every texel of its lattice."""
    from isolume.baking.plan import _gradients

    data = make("engine", 40).data
    vol = Volume((data * (200.0 if dtype == np.uint8 else 1.0)).astype(dtype),
                 spacing=(1.0, 1.2, 0.9), origin=(0.5, -1.0, 2.0))
    geometry = LatticeGeometry.for_volume(vol, 1.5)
    ids = np.arange(int(np.prod(geometry.shape)))
    h = float(np.mean(vol.spacing))
    want = np.linalg.norm(volumes.gradient_at(vol, geometry.centres(ids)), axis=1) * h
    got = _gradients(vol, geometry, ids)
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.float64 and (want > 0).mean() > 0.3
