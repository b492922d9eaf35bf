"""Which side of its surface a texel is lit on (`baking.sides`): the side a camera outside
the volume sees, both on alternate texels where both are seen.

Phantoms with a known answer: a closed ball (only its outside is seen), a ball-shaped
cavity in a solid that fills the box (only the cavity's outside, the high-value side, is
seen: the solid is cut open by every face of the box), a plane across the box (both
sides), and the cut-open slab over a shelf of `test_seen_side` and a chamber on a floor
the box cuts open, seen through a window in its roof, baked and drawn from their lattices
against `isolume reference`. Constant sky, no bounces: a texel's value is the
visible fraction of the sky times π, exactly π where nothing can block its paths.
"""

import numpy as np
import pytest
from test_seen_side import _cut_open_slab, _pictures

from isolume import volumes
from isolume.baking import BakeConfig, bake
from isolume.baking.plan import make_plan
from isolume.baking.sides import CLEARLY_MORE, CONFIRM_PROBES, PROBES, side_rule
from isolume.volumes import Volume, load
from isolume.volumes.reach import BoxReach

SKY = dict(samples=16, bounces=0, env="constant:1,1,1", seed=3)


def _ball(n: int = 24, cavity: bool = False) -> Volume:
    """A ball of radius 0.3 n (anti-aliased edge), or a cavity of that shape in a solid
    filling the box."""
    z, y, x = np.mgrid[:n, :n, :n] - (n - 1) / 2
    inside = np.clip(0.3 * n - np.sqrt(x * x + y * y + z * z) + 0.5, 0, 1)
    data = 1 - inside if cavity else inside
    return Volume(data.astype(np.float32), name="ball", source="ball")


def _plane(n: int = 16) -> Volume:
    """Solid below a plane across the box, 0.3 voxel above a voxel centre."""
    z = np.arange(n)[:, None, None] - (n / 2 + 0.3)
    data = np.broadcast_to(np.clip(0.5 - z, 0, 1), (n, n, n))
    return Volume(np.ascontiguousarray(data, np.float32), name="plane", source="plane")


def _plan(volume: Volume, **settings):
    config = BakeConfig(iso_range=(0.45, 0.55), **SKY, **settings)
    lattice = bake(volume, config, workers=2)
    return make_plan(volume, lattice.geometry, config), lattice


def test_the_rule_lights_the_open_side_and_the_normals_side_alone_only_where_clearly_more_open():
    """Both sides open: the normals' side alone where it has `CLEARLY_MORE` times the other's
    open rays, else both on alternate texels — never the other side alone (on a scan that
    is the inside of the material seen through the box's cut)."""
    low = np.array([0, 0, 5, 16, 16, 2, 3, 0, 1])
    high = np.array([0, 7, 0, 4, 2, 16, 3, 0, 16])
    odd = np.array([False, False, True, True, True, False, True, True, True])
    np.testing.assert_array_equal(side_rule(low, high, odd, False),
                                  [False, True, False, True, False, False, True, False, True])
    np.testing.assert_array_equal(side_rule(low, high, odd, True),
                                  [True, True, False, True, True, True, True, True, True])


@pytest.mark.parametrize("clearly_more", [CLEARLY_MORE, 3.0, 0.0])
def test_counts_cut_short_where_the_side_is_settled_give_the_rules_side(clearly_more,
                                                                       monkeypatch):
    """`side_kernels.probe_sides` stops counting a side's open rays once the rule's choice
    is settled: the other side at `enough_other`, the default side at `enough_open` (or
    at its first open ray where that cannot be reached). For every pair of exact counts,
    of 16 rays and of 16 + 48 confirmed, with the open rays first or last, the cut
    counts give the sides `side_rule` gives the exact counts."""
    from isolume.baking import sides
    from isolume.baking.side_kernels import enough_open, enough_other, settled_count

    monkeypatch.setattr(sides, "CLEARLY_MORE", clearly_more)

    cap = enough_other(PROBES, clearly_more)

    def cut(count: int, rays: int, need: int, settle: bool, first_open: int) -> int:
        """Open rays counted, as `open_counts` counts them, when the `count` open ones of
        `rays` come from `first_open` on."""
        opened = 0
        for s in range(rays):
            if settled_count(opened, rays - s, need, settle):
                break
            opened += first_open <= s < first_open + count
        return opened

    for other in range(PROBES + 1):
        for mine, rays in [(m, PROBES) for m in range(1, PROBES + 1)] + [
                (m, PROBES + CONFIRM_PROBES) for m in range(CONFIRM_PROBES + 1)]:
            own = mine if rays == PROBES else 0
            extra = mine if rays > PROBES else 0
            want = _sides(own + extra, other, rays)
            for place in ("first", "last"):
                got_other = cut(other, PROBES, cap, False,
                                0 if place == "first" else PROBES - other)
                assert (got_other == 0) == (other == 0)
                if got_other == 0:  # the other side closed: the default side, unprobed
                    assert want == (False, False)
                    continue
                need = enough_open(np.array([got_other]), PROBES, PROBES, clearly_more)[0]
                got = cut(own, PROBES, need, True, 0 if place == "first" else PROBES - own)
                if got == 0:
                    more = PROBES + CONFIRM_PROBES
                    need = enough_open(np.array([got_other]), PROBES, more, clearly_more)[0]
                    got = cut(extra, CONFIRM_PROBES, need, True,
                              0 if place == "first" else CONFIRM_PROBES - extra)
                    rays_seen = more
                else:
                    rays_seen = PROBES
                assert _sides(got, got_other, rays_seen) == want, (
                    other, mine, rays, place)


def _sides(mine: int, other: int, rays: int) -> tuple[bool, bool]:
    """`side_rule`'s high sides (the default side low) of an even and an odd texel whose
    default side has `mine` open rays of `rays` and whose other side `other` of
    `PROBES`."""
    return tuple(bool(side_rule(np.array([mine]), np.array([other]), np.array([odd]),
                                False, rays)[0]) for odd in (False, True))


def test_a_closed_ball_is_lit_on_its_outside():
    plan, lattice = _plan(_ball())
    assert not plan.high.any()
    assert lattice.meta["plan"]["high_side_texels"] == 0


def test_a_cavity_is_lit_on_the_side_seen_from_outside_the_box():
    """Its outside (high values) sees the whole sky: E = π exactly; lit on the normals'
    side, inside the closed cavity, it sees none of it."""
    vol = _ball(cavity=True)
    plan, lattice = _plan(vol)
    assert plan.high.all()
    values = lattice.values.reshape(-1, 3)[plan.ids, 0]
    np.testing.assert_allclose(values, np.pi, rtol=1e-5)
    _, inside = _plan(vol, sides="normals")
    assert inside.values.reshape(-1, 3)[plan.ids, 0].max() < 1e-6


def test_a_plane_across_the_box_is_lit_on_both_sides_in_a_checkerboard():
    """Both half-spaces reach the box's faces: every probe from either side leaves it."""
    vol = _plane()
    plan, lattice = _plan(vol)
    k, j, i = np.unravel_index(plan.ids, lattice.geometry.shape)
    np.testing.assert_array_equal(plan.high, ((k + j + i) % 2).astype(bool))
    assert 0.4 < plan.high.mean() < 0.6
    assert PROBES >= 16


def test_sides_chosen_a_few_texels_at_a_time_are_the_same(monkeypatch):
    """`choose_sides` probes `TEXELS_PER_BATCH` texels an item, on every core: any split
    and any number of threads give the same sides (each texel's probes are its own)."""
    from isolume.baking import sides
    from isolume.volumes import cores

    vol = _plane(24)  # both sides open: lit on alternate texels, by their ids
    config = BakeConfig(iso_range=(0.45, 0.55), **SKY)
    geometry = bake(vol, config, workers=2).geometry
    whole = make_plan(vol, geometry, config).high
    monkeypatch.setattr(sides, "TEXELS_PER_BATCH", 37)
    for threads in (1, 3):
        cores.use(threads)
        try:
            np.testing.assert_array_equal(make_plan(vol, geometry, config).high, whole)
        finally:
            cores.use(None)
    assert 0 < whole.sum() < len(whole) and len(whole) > 10 * 37


@pytest.mark.parametrize("view", [(30.0, 60.0, 1.6), (30.0, -40.0, 1.6)])
def test_a_baked_cut_open_slab_matches_the_reference_from_above_and_below(view):
    """From above the eye sees the slab's bottom face from inside (its high side, open to
    the sky through the cut); from below, the shelf's underside. Mean within 5 % of the
    reference, at most 0.5 % of its lit pixels black. Lit on the normals' side, the
    bottom face is drawn at the light of the shelf's shadow: measured 0.40 of the
    reference from above."""
    volume = _cut_open_slab()
    config = BakeConfig(iso_range=(0.45, 0.55), samples=64, bounces=0,
                        env="constant:1,1,1", seed=5)
    ratios = {}
    for sides in ("seen", "normals"):
        lattice = bake(volume, BakeConfig(**{**config.to_dict(), "sides": sides}),
                       workers=2)
        picture, truth = _pictures(volume, view, lattice)
        assert len(truth) > 500
        ratios[sides] = picture.mean() / truth.mean()
        if sides == "seen":
            lit = truth > 0.05 * truth.mean()
            assert (picture[lit] <= 0).mean() <= 0.005
    assert ratios["seen"] == pytest.approx(1.0, abs=0.05)
    if view[1] > 0:
        assert ratios["normals"] < 0.8


@pytest.mark.parametrize("dtype", [np.uint8, np.float64])
def test_compiled_probes_count_what_the_array_code_counts(dtype):
    """`side_kernels.open_counts` (one compiled call a side, as `probe_sides` calls it)
    against the array code that scenes without compiled Embree calls run (`open_rays`:
    `unblocked_rays`, embreex): the same counts for every point, on both sides, for
    either default side, the default side's confirming rays included — on the synthetic
    engine's folds (counts between 0 and 16), with NaN points and points off the level."""
    from isolume.baking.rng import seed_key
    from isolume.baking.side_kernels import open_counts
    from isolume.baking.sides import (
        CONFIRM_PROBES,
        SALT,
        level_surface,
        open_rays,
        probe_offset,
    )

    vol = load("synthetic:engine:40")
    scale = 200.0 if dtype == np.uint8 else 1.0
    vol = Volume((vol.data * scale).astype(dtype), spacing=vol.spacing, name="engine",
                 source="engine")
    level = 0.3019 * scale  # not a sample value
    scene = level_surface(vol, level)
    assert scene.calls is not None
    rng = np.random.default_rng(5)
    vertices = scene.vertices[:len(scene.faces)]
    points = vertices[rng.choice(len(vertices), 1500, replace=False)].astype(np.float64)
    points[:20] += rng.normal(0, 2.0, (20, 3))  # off the level: on neither side at times
    points[20:23] = np.nan
    ids = rng.choice(10**6, len(points), replace=False)
    config = BakeConfig(**SKY)
    normals = volumes.normals_at(vol, points).astype(np.float64)
    scratch = np.empty(1, np.result_type(vol.data.dtype, np.float32))
    fixed = (np.asarray(vol.data)[..., None], np.asarray(vol.origin, np.float64),
             np.asarray(vol.spacing, np.float64), scratch.dtype.type(level), scratch)

    reaches = {default: BoxReach.of(vol, up=not default) for default in (False, True)}

    def count(sign, which, first=0, probes=PROBES, reach=None):
        tested = (reach is not None, *(reach or reaches[False]).arrays(vol))
        return open_counts(scene.calls, np.uint32(seed_key(config.seed ^ SALT)),
                           ids.astype(np.int64), points, normals, probe_offset(vol, config),
                           sign, which, *fixed, first, probes, tested,
                           np.full(len(points), probes), False)

    compiled = []
    for default in (False, True):
        other_sign = 1.0 if default else -1.0
        other = count(other_sign, np.ones(len(points), bool), reach=reaches[default])
        mine = count(-other_sign, other > 0)
        confirmed = (other > 0) & (mine == 0)
        mine = mine + count(-other_sign, confirmed, PROBES, CONFIRM_PROBES)
        rays = np.where(confirmed, PROBES + CONFIRM_PROBES, PROBES)
        compiled.append((other, mine, rays) if default else (mine, other, rays))
    scene.calls = None
    arrays = [open_rays(scene, vol, config, ids, points, level, default, reaches[default])
              for default in (False, True)]
    for got, want in zip(compiled, arrays, strict=True):
        for side in (0, 1, 2):
            np.testing.assert_array_equal(got[side], want[side])
    assert any((got[2] > PROBES).any() for got in compiled)
    counts = np.stack([side for got in compiled for side in got[:2]])
    assert np.all(counts[:, 20:23] == 0)
    assert ((counts > 0) & (counts < PROBES)).sum() > 100 and (counts == PROBES).sum() > 100


@pytest.mark.parametrize("make_volume", [lambda: _plane(24), lambda: _ball(24, cavity=True),
                                         lambda: load("synthetic:engine:40")])
def test_sides_chosen_in_one_compiled_call_are_the_arrays_sides(make_volume, monkeypatch):
    """An item's side probes in one compiled call (`side_kernels.probe_sides`: points,
    normals, both sides' probes, the rule and the parity) against the array code that
    scenes without compiled Embree calls run: the same side for every texel of a plane
    open on both sides, a cavity and the synthetic engine."""
    from isolume.baking import trace

    vol = make_volume()
    config = BakeConfig(iso_range=(0.25, 0.55), **SKY)
    geometry = bake(vol, config, workers=2).geometry
    compiled = make_plan(vol, geometry, config).high
    monkeypatch.setattr(trace, "embree_calls", lambda scene: None)
    arrays = make_plan(vol, geometry, config).high
    np.testing.assert_array_equal(compiled, arrays)
    assert len(compiled) > 500


def _chamber(n: int = 32) -> Volume:
    """A closed chamber on a floor slab cut open by the bottom border (z ≤ 7), under a
    roof (z 20–23) with a window (x, y 12–19): the floor's top face sees the sky through
    the window only, its high side through the cut."""
    z, y, x = np.mgrid[:n, :n, :n]
    walls = (np.minimum(x, y) <= 3) | (np.maximum(x, y) >= n - 4)
    window = (x >= 12) & (x <= 19) & (y >= 12) & (y <= 19)
    solid = (z <= 7) | ((z <= 23) & walls) | ((z >= 20) & (z <= 23) & ~window)
    return Volume(solid.astype(np.float32), name="chamber", source="chamber")


def test_a_floor_seen_through_a_window_is_lit_on_the_side_the_window_shows():
    """The eye above the window sees the floor's top face (its normals' side), dimly lit
    through the window; its other side, the inside of the slab, sees the whole sky through
    the cut. Lit there alone, the floor would be drawn in the cut's light (measured 7.4
    times the reference's mean); its texels that find the window with none of their 16
    first probes are confirmed with more (`CONFIRM_PROBES`; without them 1.46 times).
    Lit on both sides in a checkerboard, the side-aware lookup shows the window's light:
    mean within 10 % of the reference (measured 1.02), at most 0.5 % of its lit pixels
    black."""
    volume = _chamber()
    config = BakeConfig(iso_range=(0.45, 0.55), samples=64, bounces=0,
                        env="constant:1,1,1", seed=5)
    picture, truth = _pictures(volume, (30.0, 80.0, 1.2), bake(volume, config, workers=2))
    floor = truth < 0.5 * truth.max()  # the roof's and walls' tops see the whole sky
    assert floor.sum() > 100
    assert picture[floor].mean() / truth[floor].mean() == pytest.approx(1.0, abs=0.1)
    assert (picture[floor] <= 0).mean() <= 0.005
