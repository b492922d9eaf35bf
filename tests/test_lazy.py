"""Lazy baking: which texels first (geometry), in what order, how many paths, re-targeting."""

import queue

import numpy as np
import pytest

from isolume import volumes
from isolume.baking.adaptive import relative_error
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.lazy import (
    LazyScheduler,
    View,
    by_distance,
    cell_index,
    corner_offsets,
    footprint_positions,
    positions_of,
    sample_targets,
    serve,
    surface_positions,
    visible_cells,
)
from isolume.baking.plan import make_plan


@pytest.fixture(scope="module")
def sphere():
    """A 24³ sphere (iso 0.5, radius 0.35 around the origin), its lattice and plan."""
    vol = volumes.load("synthetic:sphere:24")
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    plan = make_plan(vol, geometry, BakeConfig(samples=8))
    return vol, geometry, plan


def _brute_surface_texels(plan, shape, iso):
    """Flat ids of active corners of cells (all corners active) whose values straddle iso,
    by looping over every cell."""
    z, y, x = shape
    rho = np.full(z * y * x, np.nan)
    rho[plan.ids] = plan.rho
    rho = rho.reshape(shape)
    out = set()
    for k in range(z - 1):
        for j in range(y - 1):
            for i in range(x - 1):
                corners = rho[k:k + 2, j:j + 2, i:i + 2]
                if np.isnan(corners).any():
                    continue
                if corners.min() <= iso <= corners.max():
                    for dk in (0, 1):
                        for dj in (0, 1):
                            for di in (0, 1):
                                out.add(((k + dk) * y + j + dj) * x + i + di)
    return np.array(sorted(out))


def test_sample_targets_grow_and_end_at_the_bake_samples():
    assert sample_targets(100) == (4, 16, 64, 100)
    assert sample_targets(256) == (4, 16, 64, 256)
    assert sample_targets(4) == (4,)
    assert sample_targets(1) == (1,)
    with pytest.raises(ValueError):
        sample_targets(0)


def test_corner_offsets_address_the_cell_corners():
    shape = (3, 4, 5)
    grid = np.arange(60).reshape(shape)
    assert sorted(corner_offsets(shape) + grid[1, 2, 3]) == sorted(grid[1:3, 2:4, 3:5].ravel())


def test_surface_texels_are_the_corners_of_cells_straddling_the_isovalue(sphere):
    _, geometry, plan = sphere
    cells = cell_index(plan, geometry.shape)
    for iso in (0.3, 0.5, 0.7):
        got = plan.ids[surface_positions(plan, cells, iso)]
        want = _brute_surface_texels(plan, geometry.shape, iso)
        np.testing.assert_array_equal(got, want)


def test_surface_texels_surround_the_sphere(sphere):
    """Every surface texel lies within one texel diagonal of the iso 0.5 sphere (r = 0.35)."""
    _, geometry, plan = sphere
    pos = surface_positions(plan, cell_index(plan, geometry.shape), 0.5)
    r = np.linalg.norm(geometry.centres(plan.ids[pos]), axis=1)
    diag = np.linalg.norm(geometry.texel_size)
    assert len(pos) > 500
    assert np.abs(r - 0.35).max() < diag


def test_visible_footprint_holds_the_trilinear_corners(sphere):
    """The texels a lookup at p reads are the corners of the cell containing p."""
    _, geometry, plan = sphere
    rng = np.random.default_rng(1)
    d = rng.normal(size=(200, 3))
    points = 0.35 * d / np.linalg.norm(d, axis=1, keepdims=True)
    cells = visible_cells(geometry, points)
    pos = footprint_positions(plan, geometry.shape, cells)
    got = set(plan.ids[pos].tolist())
    coords = geometry.to_texel_coords(points)  # (z, y, x), centres at integers
    for c in coords:
        base = np.floor(c).astype(int)
        for corner in np.ndindex(2, 2, 2):
            k, j, i = base + np.array(corner)
            flat = (k * geometry.shape[1] + j) * geometry.shape[2] + i
            assert flat in got or len(positions_of(plan, np.array([flat]))) == 0


def test_by_distance_sorts_nearest_first(sphere):
    _, geometry, plan = sphere
    pos = surface_positions(plan, cell_index(plan, geometry.shape), 0.5)
    eye = np.array([0.0, -2.0, 0.5])
    ordered = by_distance(plan, geometry, pos, eye)
    d = np.linalg.norm(geometry.centres(plan.ids[ordered]) - eye, axis=1)
    assert np.all(np.diff(d) >= 0)
    assert sorted(ordered) == sorted(pos)


class FakeBaker:
    """Stands in for `Baker.run`: sets the sample counts of a batch to its target."""

    def __init__(self, plan, samples):
        self.plan, self.samples = plan, samples

    def bake(self, batch):
        flat = self.plan.ids[batch.positions]
        self.samples[flat] = np.maximum(self.samples[flat], batch.target)


def _scheduler(sphere, max_samples=16, batch_paths=400):
    _, geometry, plan = sphere
    samples = np.zeros(int(np.prod(geometry.shape)), np.uint32)
    sched = LazyScheduler(plan, geometry, samples, max_samples=max_samples,
                          batch_paths=batch_paths)
    return sched, FakeBaker(plan, samples), samples


def test_scheduler_bakes_visible_rounds_then_surface_rounds_nearest_first(sphere):
    _, geometry, plan = sphere
    sched, baker, _ = _scheduler(sphere)
    eye = np.array([0.0, -2.0, 0.0])
    # visible: the hemisphere facing the eye
    rng = np.random.default_rng(2)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    front = 0.35 * d[d[:, 1] < -0.3]
    sched.set_view(0.5, eye, visible_cells(geometry, front))
    assert 0 < len(sched.visible) < len(sched.surface)
    batches, paths = [], []
    while (batch := sched.next_batch()) is not None:
        batches.append(batch)
        paths.append(int((batch.target - sched.samples_at(batch.positions)).sum()))
        baker.bake(batch)
    groups = [(b.group, b.target) for b in batches]
    # stage order, each stage contiguous
    stages = list(dict.fromkeys(groups))
    assert stages == [("visible", 4), ("visible", 16), ("surface", 4), ("surface", 16)]
    # within the first stage, texels come nearest first
    first = np.concatenate([b.positions for b in batches if b.group == "visible"
                            and b.target == 4])
    d = np.linalg.norm(geometry.centres(plan.ids[first]) - eye, axis=1)
    assert np.all(np.diff(d) >= -1e-12)
    # the surface round skips what the visible round already did
    surface4 = np.concatenate([b.positions for b in batches if (b.group, b.target)
                               == ("surface", 4)])
    assert not np.isin(surface4, first).any()
    # batches respect the path budget (one texel may exceed it alone)
    for b, n in zip(batches, paths, strict=True):
        assert n <= 400 or len(b.positions) == 1
    progress = sched.progress()
    assert progress.visible_fraction == 1.0 and progress.surface_fraction == 1.0
    assert progress.stage is None and progress.visible_min_samples == 16


def test_retargeting_keeps_finished_texels(sphere):
    """Move the isovalue: texels shared by both surfaces are not baked again."""
    _, _, plan = sphere
    sched, baker, samples = _scheduler(sphere, max_samples=4)
    eye = np.array([2.0, 0.0, 0.0])
    sched.set_view(0.5, eye)
    while (batch := sched.next_batch()) is not None:
        baker.bake(batch)
    done_before = samples.copy()
    sched.set_view(0.45, eye)
    redone = []
    while (batch := sched.next_batch()) is not None:
        redone.append(plan.ids[batch.positions])
        baker.bake(batch)
    redone = np.concatenate(redone)
    assert (done_before[redone] == 0).all()
    shared = np.intersect1d(plan.ids[sched.surface], np.flatnonzero(done_before))
    assert len(shared) > 0 and not np.isin(shared, redone).any()


def test_relative_error_matches_the_standard_error_formula():
    values = np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [1.0, 1.0, 1.0]])
    # per-path luminance samples with variance known: mean 1, second moment 1.25 -> var .25
    second = np.array([1.25, 4.0, 1.0])
    n = np.array([101, 10, 1])
    err = relative_error(values, second, n)
    assert err[0] == pytest.approx(np.sqrt(0.25 * 101 / 100 / 101), rel=1e-9)
    assert err[1] == 0.0
    assert np.isinf(err[2])


def _receiver(inbox: queue.Queue):
    """``receive(block)`` for `serve`: the next message of `inbox`, None when it is empty
    (after 5 s when blocking)."""
    def receive(block):
        try:
            return inbox.get(block=block, timeout=5 if block else None)
        except queue.Empty:
            return None

    return receive


def test_serve_bakes_the_view_with_the_real_baker(sphere):
    """End to end on a tiny volume: every surface texel reaches the target, texels come
    nearer-first, and committed ids are announced."""
    from isolume.baking.bake import Baker

    vol, geometry, _ = sphere
    config = BakeConfig(samples=4, bounces=0)
    baker = Baker(vol, config, workers=2, scene_cache=64)
    plan = baker.plan
    sched = LazyScheduler(plan, geometry, baker.lattice.samples.reshape(-1), max_samples=4,
                          batch_paths=600)
    inbox, sent = queue.Queue(), []
    eye = (0.0, -2.0, 0.3)
    inbox.put(View(0.5, eye, None))
    try:
        stats = serve(baker, sched, _receiver(inbox), sent.append, stop_when_done=True)
    finally:
        baker.close()
    samples = baker.lattice.samples.reshape(-1)
    surface = plan.ids[sched.surface]
    assert (samples[surface] >= 4).all()
    texels = [m[1] for m in sent if m[0] == "texels"]
    announced = np.concatenate(texels)
    assert np.isin(surface, announced).all()
    # the first announced texels are nearer the eye than the last ones
    d_first = np.linalg.norm(geometry.centres(texels[0]) - eye, axis=1).mean()
    d_last = np.linalg.norm(geometry.centres(texels[-1]) - eye, axis=1).mean()
    assert d_first < d_last
    assert stats.batches >= 2 and stats.paths >= 4 * len(surface)
    final = [m for m in sent if m[0] == "progress"][-1][1]
    assert final.surface_fraction == 1.0 and final.stage is None
    assert (baker.lattice.values.reshape(-1, 3)[surface] > 0).all()


def test_view_iso_range_is_a_band_around_the_isovalue_within_the_data():
    from isolume.baking.lazy import VIEW_RANGE_FRACTION, view_iso_range

    vol = volumes.load("synthetic:sphere:24")
    vmin, vmax = vol.value_range
    half = VIEW_RANGE_FRACTION * (vmax - vmin)
    assert view_iso_range(vol, 0.5) == pytest.approx((0.5 - half, 0.5 + half))
    assert view_iso_range(vol, vmin + half / 2)[0] == vmin


def test_carry_over_keeps_texels_lit_at_the_same_target():
    """Two plans of overlapping ranges: a texel keeps its samples when both light it at
    the same target isovalue (`plan.lit_isovalues`: its own value where every isovalue
    that can read it lies in both ranges); the others — lit on another isovalue, or
    inactive now — are reset and returned."""
    from isolume.baking.bake import Baker
    from isolume.baking.lazy import carry_over

    vol = volumes.load("synthetic:shells:24")
    old = Baker(vol, BakeConfig(samples=2, bounces=0, iso_range=(0.0, 0.6)), workers=2)
    try:
        old.run()
    finally:
        old.close()
    lattice = old.lattice
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    new = make_plan(vol, geometry, BakeConfig(samples=2, bounces=0, iso_range=(0.2, 1.0)))
    before = lattice.samples.reshape(-1).copy()
    reset = carry_over(lattice, old.plan, new)
    pos = np.searchsorted(new.ids, old.plan.ids)
    inside = pos < len(new.ids)
    inside[inside] = new.ids[pos[inside]] == old.plan.ids[inside]
    same = np.zeros(len(old.plan.ids), bool)
    same[inside] = new.target[pos[inside]] == old.plan.target[inside]
    samples = lattice.samples.reshape(-1)
    assert same.any() and (~same).any()
    np.testing.assert_array_equal(samples[old.plan.ids[same]], before[old.plan.ids[same]])
    assert (samples[old.plan.ids[~same]] == 0).all()
    np.testing.assert_array_equal(np.sort(reset), np.sort(old.plan.ids[~same]))
    assert (lattice.values.reshape(-1, 3)[reset] == 0).all()


def test_serve_returns_a_view_its_plan_does_not_serve(sphere):
    """A view outside the plan's iso range ends the loop before any batch is baked for
    it; the caller plans again."""
    from isolume.baking.bake import Baker

    vol, geometry, _ = sphere
    baker = Baker(vol, BakeConfig(samples=4, bounces=0, iso_range=(0.45, 0.55)), workers=2)
    sched = LazyScheduler(baker.plan, geometry, baker.lattice.samples.reshape(-1),
                          max_samples=4)
    outside = View(0.8, (0.0, -2.0, 0.0), None)
    messages = [View(0.5, (0.0, -2.0, 0.0), None)]

    def receive(block):
        return messages.pop(0) if messages else None

    def send(message):  # the outside view comes once a batch of the first was baked
        if message[0] == "texels" and outside not in sent:
            sent.append(outside)
            messages.append(outside)

    sent: list = []
    lo, hi = baker.plan.iso_range
    try:
        stats = serve(baker, sched, receive, send, accepts=lambda view: lo <= view.iso <= hi)
    finally:
        baker.close()
    assert stats.outside is outside and sched.iso == 0.5 and stats.views == 1


def test_the_lazy_bake_plans_again_when_the_view_leaves_its_range():
    """The viewer's lazy bake of a fresh lattice bakes for the isovalues around the view;
    an isovalue outside them makes it plan again for the new one (the panel says so),
    and the new plan's texels get samples."""
    import time

    from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta
    from isolume.baking.lazy import view_iso_range

    vol = volumes.load("synthetic:shells:24")
    config = BakeConfig(samples=4, bounces=0, env="constant:1")
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    meta = lattice_meta(vol, config)
    shared = SharedLattice.create(geometry, meta["channels"], meta)
    link = BakeLink(vol, config, shared, 1, 0.3, follow_iso=True)

    def wait_ready(deadline):
        while link.ready is None and link.error is None and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.05)
        assert link.error is None and link.ready is not None
        return link.ready["meta"]["plan"]["iso_range"]

    try:
        deadline = time.monotonic() + 120
        link.send_view(View(0.3, (0.0, -2.0, 0.0), None))
        assert wait_ready(deadline) == pytest.approx(view_iso_range(vol, 0.3))
        link.send_view(View(0.6, (0.0, -2.0, 0.0), None))
        while link.replans == 0 and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.05)
        assert link.replans == 1
        assert wait_ready(deadline) == pytest.approx(view_iso_range(vol, 0.6))
        assert link.ready["config"]["iso_range"] == pytest.approx(
            view_iso_range(vol, 0.6))
        while link.near_fraction(0.6) != 1.0 and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.05)
        assert link.near_fraction(0.6) == 1.0
    finally:
        link.stop()
        shared.close()


def test_new_texels_are_drawn_at_a_pace_that_leaves_the_bake_the_processor():
    from isolume.app.viewer.window import BAKE_FRAME_SPACING, BAKE_REFRESH_S, bake_frame_due

    assert bake_frame_due(10.0, None, None)  # nothing drawn yet
    assert not bake_frame_due(10.0 + BAKE_REFRESH_S / 2, 10.0, 0.01)  # fast frames: by time
    assert bake_frame_due(10.0 + BAKE_REFRESH_S, 10.0, 0.01)
    slow = 0.8  # a slow frame: wait several of its durations
    assert not bake_frame_due(10.0 + BAKE_FRAME_SPACING * slow * 0.9, 10.0, slow)
    assert bake_frame_due(10.0 + BAKE_FRAME_SPACING * slow + 1e-9, 10.0, slow)


def _served(volume, config, target_error=None, workers=2):
    """A lazy bake of `volume`'s surface (no visible cells) to `config.samples`, its rounds
    judged by their noise to `target_error` (None: not judged), on `workers` threads;
    returns (the baker's lattice, the scheduler, the paths traced)."""
    from isolume.baking.bake import Baker

    baker = Baker(volume, config, workers=workers, scene_cache=64)
    judged = {} if target_error is None else {"judged_by": baker,
                                              "target_error": target_error}
    sched = LazyScheduler(baker.plan, baker.geometry, baker.lattice.samples.reshape(-1),
                          max_samples=config.samples, batch_paths=1 << 14, **judged)
    inbox = queue.Queue()
    inbox.put(View(0.5, (0.0, -2.0, 0.3), None))
    try:
        stats = serve(baker, sched, _receiver(inbox), lambda _message: None,
                      stop_when_done=True)
    finally:
        baker.close()
    return baker.lattice, sched, stats.paths


def test_judged_rounds_rest_where_the_noise_is_below_the_target():
    """A sphere a voxel above a plane under a constant sky, no bounces: a path brings the
    sky or nothing, so a texel's per-path variance is p(1 − p) of its open fraction p —
    none on the open top, most in the gap. Rounds from 64 paths on take only the texels
    that need more for the group's RMS standard error to be the target t times its light
    level B; a texel stops with at least half the paths its spread σ needs (n* = σ·σ̄ /
    (tB)²), so over the group the mean of SE² = σ²/n is at most 2 (tB)²: RMS SE / B ≤
    √2 t (1.25× for B and σ̄ moving between judgements; measured 0.040 at t = 0.05), and
    not far below t where no texel is held at the cap or at the first rounds. Rounds at
    every texel to 256 paths trace 5.8 times as many. One thread judges the same."""
    from isolume.baking.lattice import LUMINANCE, path_variance

    volume = volumes.load("synthetic:contact:28")
    config = BakeConfig(samples=256, bounces=0, env="constant:1,1,1", seed=2)
    target = 0.05
    lattice, sched, paths = _served(volume, config, target)
    _, _, every = _served(volume, config)
    ids = sched.plan.ids[sched.surface]
    samples = lattice.samples.reshape(-1)[ids].astype(np.int64)
    lum = lattice.values.reshape(-1, 3)[ids] @ LUMINANCE
    variance = path_variance(lum, lattice.second.reshape(-1)[ids], samples)
    assert set(np.unique(samples)) == {16, 64}
    assert (variance[samples == 16] == 0).mean() > 0.9  # all open or all blocked
    rms = np.sqrt(np.mean(variance / samples)) / np.mean(lum)
    assert 0.5 * target <= rms <= 1.25 * np.sqrt(2) * target
    assert paths < 0.3 * every
    alone, _, _ = _served(volume, config, target, workers=1)
    np.testing.assert_array_equal(alone.samples, lattice.samples)
    np.testing.assert_array_equal(alone.values, lattice.values)
