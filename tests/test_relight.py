"""A light turned in the viewer: the lazy bake re-bakes the lattice around the view for it
(`baking.lazy.Relight`), the old light's values staying on screen until the new ones rest
on enough paths, and never averaged with them."""

import dataclasses
import math

import numpy as np
import pytest

import volumes
from baking.bake import Baker
from baking.config import BakeConfig
from baking.lattice import LUMINANCE, Lattice
from baking.lazy import (
    RELIGHT_PATHS,
    LazyScheduler,
    Relight,
    View,
    relit_config,
    same_direction,
    serve,
    turned_light,
)

SUN = "sky:sun=6,sun_az=-150,sun_el=40"
ISO = 0.3
SAMPLES = 64
EYE = (0.0, -3.0, 1.0)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _config(**kw):
    return BakeConfig(**{"samples": SAMPLES, "bounces": 1, "env": SUN,
                         "iso_range": (0.25, 0.35), **kw})


@pytest.fixture(scope="module")
def engine():
    return volumes.load("synthetic:engine:48")


def _with_previews(lattice: Lattice) -> Lattice:
    """`lattice` with (empty) preview arrays, as the viewer's shared lattice has them."""
    lattice.preview = np.zeros_like(lattice.values)
    lattice.preview_paths = np.zeros(lattice.samples.shape, np.uint16)
    return lattice


def _serve_view(baker, samples, *, send=None, until=None, eye=EYE):
    """Bake the surface at ISO seen from `eye` lazily (`serve`) into the lattice whose flat
    sample counts are `samples`, to the end or until `until()` is true after a commit.
    Returns the scheduler and `serve`'s stats."""
    scheduler = LazyScheduler(baker.plan, baker.geometry, samples, max_samples=SAMPLES,
                              batch_paths=20_000)
    inbox, stopped = [View(ISO, eye, None)], []

    def receive(block):
        if inbox:
            return inbox.pop(0)
        if stopped or not (block or (until is not None and until())):
            return None
        stopped.append(True)
        return "stop"

    stats = serve(baker, scheduler, receive, send or (lambda message: None),
                  stop_when_done=True)
    return scheduler, stats


def _turn(baker, lattice, direction):
    """Turn the bake's light to `direction`: a `Relight` of `lattice`, the baker tracing
    into its fresh lattice."""
    relight = Relight(lattice, relit_config(baker.config, direction))
    baker.relight(relight.config, relight.fresh)
    return relight


# -- the turned config ----------------------------------------------------------------------
def test_relit_config_turns_the_sun_or_the_first_directional_light():
    d = _unit((0.6, 0.3, 0.5))
    sky = BakeConfig(env="sky:zenith=0.2,0.4,1,sun=6,sun_az=-150,sun_el=40,sun_radius=2")
    turned = relit_config(sky, d)
    np.testing.assert_allclose(turned_light(turned), d, atol=1e-8)
    assert "zenith=0.2,0.4,1" in turned.env and "sun_radius=2" in turned.env
    assert turned.lights == () and turned.samples == sky.samples
    # a sky without sun_az/sun_el (their defaults) turns as well
    np.testing.assert_allclose(turned_light(relit_config(BakeConfig(env="sky:sun=3"), d)), d,
                               atol=1e-8)
    lit = BakeConfig(env=SUN, lights=("point:0,0,2:1,1,1", "dir:0,0,1:2,1,1",
                                       "dir:1,0,0:1,1,1"))
    turned = relit_config(lit, d)
    assert turned.env == SUN and turned.lights[0] == lit.lights[0]
    assert turned.lights[1].endswith(":2,1,1") and turned.lights[2] == lit.lights[2]
    np.testing.assert_allclose(turned_light(turned), d, atol=1e-8)
    assert same_direction(turned_light(turned), d)
    assert not same_direction(d, _unit((0.6, 0.3, 0.52)))  # ~1.4°


def test_nothing_to_turn_in_an_sh_transfer_or_a_lattice_holding_its_direct_light():
    """An SH transfer (split or not) turns its sky and sun with the transfer, and a
    lattice with the direct light inside shows no per-pixel light: no relight for them."""
    assert turned_light(BakeConfig(mode="sh", env=SUN, direct_light="pixels")) is None
    assert turned_light(BakeConfig(mode="sh", env=SUN)) is None
    assert turned_light(BakeConfig(env=SUN, direct_light="lattice")) is None
    assert turned_light(BakeConfig(env="constant:1")) is None
    with pytest.raises(ValueError, match="no per-pixel"):
        relit_config(BakeConfig(env="constant:1"), (0, 0, 1))


# -- the re-bake ----------------------------------------------------------------------------
def _empty(volume, config):
    """An empty lattice for `config` on `volume`, with the preview arrays the viewer's
    shared lattice has."""
    from app.viewer_bake import lattice_meta
    from baking.lattice import LatticeGeometry

    meta = lattice_meta(volume, config)
    lattice = Lattice.empty(LatticeGeometry.for_volume(volume, config.scale),
                            meta["channels"], meta)
    lattice.preview = np.zeros_like(lattice.values)
    lattice.preview_paths = np.zeros(lattice.samples.shape, np.uint16)
    return lattice


def _state(lattice, ids):
    """(values, samples, second, preview, preview_paths) of the texels `ids`."""
    return (lattice.values.reshape(-1, 3)[ids].copy(), lattice.samples.reshape(-1)[ids].copy(),
            lattice.second.reshape(-1)[ids].copy(), lattice.preview.reshape(-1, 3)[ids].copy(),
            lattice.preview_paths.reshape(-1)[ids].copy())


def _same(a, b):
    """(K,) bool: texels whose whole state is equal in the `_state` tuples `a` and `b`."""
    equal = np.ones(len(a[1]), bool)
    for x, y in zip(a, b, strict=True):
        equal &= (x == y).reshape(len(equal), -1).all(axis=1)
    return equal


def _lum(values):
    return values.astype(np.float64) @ LUMINANCE


@pytest.fixture(scope="module")
def relit(engine):
    """The surface around a view baked under the default sun, then the sun turned and the
    same surface baked again lazily (published as it went)."""
    config = _config()
    baker = Baker(engine, config, lattice=_empty(engine, config), workers=2, scene_cache=64)
    try:
        lattice = baker.lattice
        _serve_view(baker, lattice.samples.reshape(-1))
        ids = baker.plan.ids
        old = _state(lattice, ids)
        relight = _turn(baker, lattice, _unit((0.6, 0.3, 0.5)))
        scheduler, _ = _serve_view(baker, relight.fresh.samples.reshape(-1),
                                   send=relight.forward(lambda message: None))
    finally:
        baker.close()
    return baker, relight, scheduler, old


def test_a_relit_lattice_is_a_fresh_bake_under_the_turned_light(engine, relit):
    """Every surface texel of the view shows the new light's estimate; with the same seed
    it is the estimate a bake under that light from scratch gives (the same paths, to
    float32 rounding of the running means), and against one of another seed it agrees
    within the noise of SAMPLES paths per texel — region by region — while it differs
    from the old light's by many times that noise."""
    baker, relight, scheduler, old = relit
    shown = relight.shown
    ids = baker.plan.ids[scheduler.surface]
    assert len(ids) > 5000 and relight.published[ids].all()
    assert (shown.samples.reshape(-1)[ids] == SAMPLES).all()
    assert _same(_state(shown, ids), _state(relight.fresh, ids)).all()
    for seed in (0, 1):
        fresh = Baker(engine, dataclasses.replace(relight.config, seed=seed), workers=2,
                      scene_cache=64)
        try:
            fresh.run(scheduler.surface, SAMPLES)
        finally:
            fresh.close()
        want = fresh.lattice.values.reshape(-1, 3)[ids]
        got = shown.values.reshape(-1, 3)[ids]
        if seed == 0:
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
            continue
        se = np.sqrt(shown.standard_error().reshape(-1)[ids].astype(np.float64) ** 2
                     + fresh.lattice.standard_error().reshape(-1)[ids] ** 2)
        assert np.isfinite(se).all()
        diff = _lum(got) - _lum(want)
        centres = baker.geometry.centres(ids)
        octant = ((centres > centres.mean(axis=0)) * (1, 2, 4)).sum(axis=1)
        for k in range(8):  # the mean of a region's differences: within 4 of its sigmas
            group = octant == k
            noise = math.sqrt(float((se[group] ** 2).sum())) / group.sum()
            assert abs(diff[group].mean()) < 4 * noise, (k, diff[group].mean(), noise)
        before = old[0][np.searchsorted(baker.plan.ids, ids)]
        noise = math.sqrt(float((se ** 2).sum())) / len(ids)
        assert abs((_lum(got) - _lum(before)).mean()) > 10 * noise  # the turn mattered


def test_a_texel_shows_the_old_light_or_the_new_never_a_mix(engine):
    """Stopped half-way through the re-bake: every texel holds either the old light's whole
    state (mean, samples, second moment, preview) or the new light's, and the new one only
    where it rests on RELIGHT_PATHS paths (the old ones rested on more)."""
    config = dataclasses.replace(_config(), seed=3)
    baker = Baker(engine, config, lattice=_empty(engine, config), workers=2, scene_cache=64)
    try:
        lattice = baker.lattice
        _serve_view(baker, lattice.samples.reshape(-1))
        ids = baker.plan.ids
        old = _state(lattice, ids)
        relight = _turn(baker, lattice, _unit((-0.2, 0.9, 0.4)))
        published = relight.published
        scheduler, stats = _serve_view(
            baker, relight.fresh.samples.reshape(-1), send=relight.forward(lambda m: None),
            until=lambda: published.sum() > 3000)
    finally:
        baker.close()
    assert stats.interrupted + stats.batches > 0
    surface = ids[scheduler.surface]
    now, fresh = _state(lattice, ids), _state(relight.fresh, ids)
    new = published[ids]
    assert 3000 < new.sum() < len(surface)  # half-way
    assert _same(now, fresh)[new].all()
    assert _same(now, old)[~new].all()
    assert (relight.fresh.samples.reshape(-1)[ids[new]] >= RELIGHT_PATHS).all()
    assert (relight.fresh.samples.reshape(-1)[ids[~new]] < RELIGHT_PATHS).all()
    assert (old[1][new] == SAMPLES).all()
    # the counts on screen are one light's: the old light's 64, or the new one's
    assert set(np.unique(now[1][new])) <= {16, 64} and (now[1][~new] == SAMPLES)[
        np.isin(ids[~new], surface)].all()


def test_turning_twice_keeps_only_the_last_directions_work(engine):
    """Turned to one direction, then, half-way, to another: what is on screen in the end is
    the last direction's bake alone (a bake under it from scratch, to rounding); a later
    view under the same light keeps that work (nothing traced again)."""
    config = _config()
    baker = Baker(engine, config, lattice=_empty(engine, config), workers=2, scene_cache=64)
    try:
        lattice = baker.lattice
        _serve_view(baker, lattice.samples.reshape(-1))
        first = _turn(baker, lattice, _unit((0.6, 0.3, 0.5)))
        _serve_view(baker, first.fresh.samples.reshape(-1), send=first.forward(lambda m: None),
                    until=lambda: first.published.sum() > 3000)
        assert first.published.any()
        last = _turn(baker, lattice, _unit((-0.7, -0.2, 0.3)))
        scheduler, _ = _serve_view(baker, last.fresh.samples.reshape(-1),
                                   send=last.forward(lambda m: None))
        _, again = _serve_view(baker, last.fresh.samples.reshape(-1),
                               send=last.forward(lambda m: None), eye=(3.0, 0.0, 0.5))
    finally:
        baker.close()
    assert again.paths == 0
    surface = baker.plan.ids[scheduler.surface]
    assert last.published[surface].all()
    scratch = Baker(engine, last.config, workers=2, scene_cache=64)
    try:
        scratch.run(scheduler.surface, SAMPLES)
    finally:
        scratch.close()
    np.testing.assert_allclose(lattice.values.reshape(-1, 3)[surface],
                               scratch.lattice.values.reshape(-1, 3)[surface], rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_array_equal(lattice.samples.reshape(-1)[surface], SAMPLES)


def test_a_new_estimate_replaces_one_that_rested_on_fewer_paths_sooner():
    """`Relight.needed`: RELIGHT_PATHS, or as many paths as the old value had (a preview's
    or its own) when fewer; 1 where nothing was shown."""
    from baking.lattice import LatticeGeometry

    geometry = LatticeGeometry((1, 1, 4), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    shown = _lattice_of(geometry)
    shown.samples[0, 0] = (0, 4, 64, 0)
    shown.preview_paths[0, 0] = (0, 0, 0, 8)
    relight = Relight(shown, BakeConfig(env=SUN))
    np.testing.assert_array_equal(relight.needed(np.arange(4)), [1, 4, RELIGHT_PATHS, 8])
    relight.fresh.samples[0, 0] = (1, 4, RELIGHT_PATHS - 1, 4)
    relight.fresh.preview_paths[0, 0] = (0, 0, 0, 8)
    relight.fresh.values[0, 0] = 7.0
    np.testing.assert_array_equal(relight.publish(np.arange(4)), [0, 1, 3])
    np.testing.assert_array_equal(shown.values[0, 0, :, 0], [7, 7, 0, 7])
    np.testing.assert_array_equal(shown.samples[0, 0], [1, 4, 64, 4])


def _lattice_of(geometry):
    lattice = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    lattice.preview = np.zeros_like(lattice.values)
    lattice.preview_paths = np.zeros(lattice.samples.shape, np.uint16)
    return lattice
