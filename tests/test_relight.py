"""A light turned in the viewer: the lazy bake re-bakes the lattice around the view for it
(`baking.lazy.Relight`), the old light's values staying on screen until the new ones rest
on enough paths, and never averaged with them."""

import dataclasses
import math
import time

import numpy as np
import pytest
from test_viewer import _view, display  # noqa: F401  (a fixture: Xvfb for the viewer)

from isolume import volumes
from isolume.app.viewer.panel import direction_from_angles
from isolume.baking.bake import Baker
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import LUMINANCE, Lattice
from isolume.baking.lazy import (
    RELIGHT_PATHS,
    LazyScheduler,
    Relight,
    View,
    cell_index,
    relit_config,
    same_direction,
    serve,
    surface_positions,
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
    from isolume.baking.lazy import new_lattice

    lattice = new_lattice(volume, config)
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


def _baked_then_turned(engine, config, direction, until=None):
    """The surface around a view baked under `config`'s sun, then the sun turned to
    `direction` and the same surface baked again lazily (published as it went; stopped
    after a commit once `until(relight)` holds).

    Returns:
        the (closed) baker, its lattice, the old `_state` of the plan's texels, the
        `Relight`, the re-bake's scheduler and `serve` stats.
    """
    baker = Baker(engine, config, lattice=_empty(engine, config), workers=2, scene_cache=64)
    try:
        lattice = baker.lattice
        _serve_view(baker, lattice.samples.reshape(-1))
        old = _state(lattice, baker.plan.ids)
        relight = _turn(baker, lattice, direction)
        scheduler, stats = _serve_view(
            baker, relight.fresh.samples.reshape(-1), send=relight.forward(lambda m: None),
            until=None if until is None else lambda: until(relight))
    finally:
        baker.close()
    return baker, lattice, old, relight, scheduler, stats


@pytest.fixture(scope="module")
def relit(engine):
    """The surface around a view baked under the default sun, then the sun turned and the
    same surface baked again lazily."""
    baker, _, old, relight, scheduler, _ = _baked_then_turned(engine, _config(),
                                                              _unit((0.6, 0.3, 0.5)))
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
    baker, lattice, old, relight, scheduler, stats = _baked_then_turned(
        engine, dataclasses.replace(_config(), seed=3), _unit((-0.2, 0.9, 0.4)),
        until=lambda relight: relight.published.sum() > 3000)
    ids, published = baker.plan.ids, relight.published
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
    from isolume.baking.lattice import LatticeGeometry

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


class _Watched(np.ndarray):
    """An array that calls `after_write` (when set) after every item assignment, to
    itself or to a view of it."""

    after_write = None

    def __setitem__(self, key, value):
        super().__setitem__(key, value)
        if _Watched.after_write is not None:
            _Watched.after_write()


def test_a_display_reading_while_a_texel_is_published_never_sees_it_black():
    """`Relight.publish` replaces a texel that shows its old light's own 8-path mean by a
    new estimate that rests on a 64-path preview alone (no samples of its own yet): after
    every array write, what a display reads (`Lattice.displayed`) is the old light's or
    the new light's value, or nothing (the display's fallback) — never 0 with a count
    vouching for it."""
    from isolume.baking.lattice import LatticeGeometry

    geometry = LatticeGeometry((1, 1, 2), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    shown = _lattice_of(geometry)
    for name in ("values", "samples", "preview", "preview_paths", "second", "facing"):
        setattr(shown, name, getattr(shown, name).view(_Watched))
    shown.samples[0, 0] = (8, 64)
    shown.values[0, 0] = 1.0
    relight = Relight(shown, BakeConfig(env=SUN))
    relight.fresh.preview_paths[0, 0] = (64, 0)
    relight.fresh.preview[0, 0] = 2.0
    relight.fresh.samples[0, 0] = (0, RELIGHT_PATHS)
    relight.fresh.values[0, 0, 1] = 3.0
    seen = []

    def read() -> None:
        values = shown.displayed()[0, 0, :, 0]
        counts = np.maximum(shown.samples[0, 0], shown.preview_paths[0, 0])
        seen.append(tuple(values))
        assert ((counts == 0) | (values > 0)).all(), (values, counts)

    _Watched.after_write = read
    try:
        np.testing.assert_array_equal(relight.publish(np.arange(2)), [0, 1])
    finally:
        _Watched.after_write = None
    assert seen[-1] == (2.0, 3.0) and {v[0] for v in seen} <= {0.0, 1.0, 2.0}


class _Racing(np.ndarray):
    """An array that runs `_Racing.writer` (when set) once, right after the
    `_Racing.at`-th read of a region of any `_Racing` array: another process writing
    the lattice in the middle of a display's reads."""

    writer = None
    at = 0
    reads = 0

    def __getitem__(self, key):
        item = super().__getitem__(key)
        _Racing.reads += 1
        if _Racing.writer is not None and _Racing.reads == _Racing.at:
            write, _Racing.writer = _Racing.writer, None
            write()
        return item


@pytest.mark.parametrize("step", ["first own samples", "first preview"])
def test_a_display_read_while_a_texel_is_written_shows_it_whole_or_not_at_all(step):
    """`Lattice.display` (what an upload reads) while the bake process commits a texel —
    its means, then its count — between any two of the display's reads: the texel is
    shown with the mean its count vouches for (before or after the commit), or not shown
    with no light; never shown black, nor hidden with light (too bright in the shader,
    which divides by the shown neighbours' weight)."""
    from isolume.baking.lattice import LatticeGeometry

    geometry = LatticeGeometry((1, 1, 1), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    for at in range(1, 40):
        lattice = _lattice_of(geometry)
        for name in ("values", "samples", "preview", "preview_paths", "facing"):
            setattr(lattice, name, getattr(lattice, name).view(_Racing))
        if step == "first own samples":  # a previewed texel gets its first 16 samples
            lattice.preview_paths[...] = 4
            lattice.preview[...] = 2.0
            mean, count, valid = lattice.values, lattice.samples, {2.0, 5.0}
        else:  # a texel without light gets its first preview
            mean, count, valid = lattice.preview, lattice.preview_paths, {5.0}

        def commit(mean=mean, count=count):
            mean[...] = 5.0
            count[...] = 16

        _Racing.writer, _Racing.at, _Racing.reads = commit, at, 0
        try:
            shown, _, values = lattice.display()
        finally:
            _Racing.writer = None
        value = float(values.reshape(-1)[0])
        assert (value in valid) if shown.all() else value == 0.0, (at, shown, value)


@pytest.mark.parametrize("relit", [False, True])
def test_a_save_while_a_texel_is_committed_holds_it_whole_or_not_at_all(relit):
    """`SharedLattice.snapshot` (what the viewer saves while the bake goes on) taken while
    the bake process re-commits a texel — its mean, then its count — between any two of
    the snapshot's reads: the file holds the texel's old pair (8 paths, 1.0) or its new
    one (16, 5.0), or leaves it out; never a count with another estimate's mean."""
    from isolume.app.viewer.bake_client import SharedLattice
    from isolume.baking.lattice import LatticeGeometry

    geometry = LatticeGeometry((1, 1, 1), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    for at in range(1, 40):
        lattice = _lattice_of(geometry)
        for name in ("values", "samples", "second", "facing"):
            setattr(lattice, name, getattr(lattice, name).view(_Racing))
        lattice.samples[...], lattice.values[...] = 8, 1.0
        shared = SharedLattice(lattice, [], owner=False,
                               relit=np.ones(geometry.shape, bool).view(_Racing))

        def commit(lattice=lattice):
            lattice.values[...] = 5.0
            lattice.samples[...] = 16

        _Racing.writer, _Racing.at, _Racing.reads = commit, at, 0
        try:
            saved = shared.snapshot(relit=relit)
        finally:
            _Racing.writer = None
        pair = (int(saved.samples.reshape(-1)[0]), float(saved.values.reshape(-1)[0]))
        assert pair in {(8, 1.0), (16, 5.0), (0, 0.0)}, (at, pair)


def _lattice_of(geometry):
    lattice = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    lattice.preview = np.zeros_like(lattice.values)
    lattice.preview_paths = np.zeros(lattice.samples.shape, np.uint16)
    return lattice


# -- the viewer's side ----------------------------------------------------------------------
def _wait(link, done, deadline, what):
    while not done() and link.error is None and time.monotonic() < deadline:
        link.poll()
        time.sleep(0.05)
    assert link.error is None, link.error
    assert done(), what


def test_the_viewers_lazy_bake_relights_a_turned_sun():
    """The lazy-bake process (`app.viewer.bake_client`) of the viewer, sent a view whose sun was
    turned, then turned again while it re-bakes: it reports the re-bake until every texel
    around the view shows the last sun's bake — the lattice a bake under that sun gives
    from scratch, to rounding: nothing of the first turn's — and a saved lattice holds only
    those texels, with the last sun in its config."""
    from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.lazy import view_iso_range, visible_cells

    vol = volumes.load("synthetic:engine:32")
    config = BakeConfig(samples=16, bounces=1, env=SUN)
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    meta = lattice_meta(vol, config)
    shared = SharedLattice.create(geometry, meta["channels"], meta)
    link = BakeLink(vol, config, shared, 2, ISO, follow_iso=True)
    mesh = volumes.isosurface(vol, ISO)
    front = mesh.vertices[mesh.vertices[:, 1] < np.median(mesh.vertices[:, 1])]
    cells = visible_cells(geometry, front)
    baked, turned = tuple(turned_light(config)), tuple(_unit((0.6, 0.3, 0.5)))
    abandoned = tuple(_unit((-0.5, -0.5, 0.6)))

    def finished():
        p = link.progress
        return p is not None and p.stage is None and p.iso == ISO

    try:
        deadline = time.monotonic() + 120
        link.send_view(View(ISO, EYE, cells, baked))
        _wait(link, finished, deadline, "the first bake")
        assert link.relit_config is None and link.relit_line(baked, "sun") is None
        link.progress = None
        link.send_view(View(ISO, EYE, cells, abandoned))
        _wait(link, lambda: link.relit is not None, deadline, "the first turn's re-bake")
        link.send_view(View(ISO, EYE, cells, turned))
        assert link.relit_line(turned, "sun").startswith("Bounced light: re-baking")
        _wait(link, lambda: link.relit_fraction(turned) == 1.0 and finished(), deadline,
              "the re-bake")
        status = link.relit
        assert status["surface_done"] == status["surface"] > 0 and status["visible"] > 0
        assert link.relit_line(turned, "sun") == "Bounced light: up to date with the turned sun."
        assert link.relit_line(baked, "sun") is None  # drawn elsewhere: not this bake's
        first, turn = link.turns
        assert first["direction"] == list(abandoned) and turn["direction"] == list(turned)
        assert 0 < turn["started_s"] <= turn["visible_s"] <= turn["surface_s"]
        relit = relit_config(dataclasses.replace(config, iso_range=view_iso_range(vol, ISO)),
                             turned)
        assert link.relit_config == relit
        saved = link.snapshot(shared)
        assert saved.config == relit
        shown = shared.lattice
        on_screen = shared.relit.reshape(-1)
        scratch = Baker(vol, relit, workers=2)
        try:
            positions = np.searchsorted(scratch.plan.ids, np.flatnonzero(on_screen))
            assert (scratch.plan.ids[positions] == np.flatnonzero(on_screen)).all()
            scratch.run(positions, config.samples)
        finally:
            scratch.close()
        ids = np.flatnonzero(on_screen & (shown.samples.reshape(-1) == config.samples))
        assert len(ids) >= status["surface"]
        np.testing.assert_allclose(shown.values.reshape(-1, 3)[ids],
                                   scratch.lattice.values.reshape(-1, 3)[ids], rtol=1e-5,
                                   atol=1e-6)
        np.testing.assert_array_equal(saved.samples.reshape(-1)[~on_screen], 0)
        np.testing.assert_array_equal(saved.samples.reshape(-1)[on_screen],
                                      shown.samples.reshape(-1)[on_screen])
    finally:
        link.stop()
        shared.close()


def test_the_viewer_turns_the_bounced_light_of_irradiance_lattices_only(gl):
    """What the viewer asks the lazy bake to follow (`Drawing.turned_light`): the sun as
    drawn per pixel in the irradiance modes of a split lattice; nothing for an SH
    transfer (its sun turns with the transfer) nor in local shading modes."""
    from isolume.app.viewer.draw import Drawing, ViewState
    from isolume.app.viewer.panel import direction_from_angles
    from isolume.baking.lazy import new_lattice

    vol = volumes.load("synthetic:sphere:16")
    drawing = Drawing(gl, vol)
    try:
        for mode, config in (("irradiance", BakeConfig(env=SUN)),
                             ("sh", BakeConfig(mode="sh", sh_order=3, env=SUN,
                                               direct_light="pixels"))):
            assert drawing.show_lattice(new_lattice(vol, config)) is None
            state = ViewState(0.5, mode, 1.0)
            if mode == "sh":
                assert drawing.turned_light(state) is None
                state.light = (30.0, 20.0)
                assert drawing.turned_light(state) is None
                continue
            name, baked = drawing.turned_light(state)
            np.testing.assert_allclose(baked, turned_light(config), atol=1e-9)
            state.light = (30.0, 20.0)
            name, turned = drawing.turned_light(state)
            assert name == "sun"
            np.testing.assert_allclose(turned, direction_from_angles(30.0, 20.0), atol=1e-9)
            assert drawing.turned_light(ViewState(0.5, "phong_hemi", 1.0, (30.0, 20.0))) is None
    finally:
        drawing.release()
    assert gl.error == "GL_NO_ERROR"


FILE_SESSION = """
wait-mesh
mode irradiance
wait-light 1 30
screenshot before.png
light 60 40
wait-light 1 120
screenshot after.png
wait-bake 0.2 120
save-lattice
quit
"""


def test_a_complete_lattice_file_is_re_baked_for_a_turned_sun(display, tmp_path):  # noqa: F811
    """``view --lattice FILE`` of a complete bake: turning its sun starts a lazy bake with
    the file's config that re-bakes the bounced light around the view; the picture's
    bounced light changes, the file keeps its whole bake, and ``save-lattice`` writes
    the turned sun's texels beside it (once the bake, not only the previews that put the
    turned light on screen first, has reached a fifth of the texels near the surface)."""
    import json

    from isolume.app.render.images import read_exr
    from isolume.baking.bake import bake

    vol = volumes.load("synthetic:engine:48")
    config = _config(samples=8)
    lattice_file = tmp_path / "light.npz"
    bake(vol, config, out=lattice_file, workers=2)
    original = lattice_file.read_bytes()
    (tmp_path / "s.txt").write_text(FILE_SESSION)
    run = _view(["synthetic:engine:48", "--iso", str(ISO), "--lattice", "light.npz",
                 "--size", "320x240", "--script", "s.txt", "--stats", "stats.json"],
                display, tmp_path)
    assert run.returncode == 0, run.stderr
    assert lattice_file.read_bytes() == original
    (turn,) = json.loads((tmp_path / "stats.json").read_text())["bake"]["turns"]
    assert 0 < turn["started_s"] <= turn["visible_s"]
    relit = Lattice.load(tmp_path / "light-relit.npz", vol)
    want = relit_config(config, direction_from_angles(60.0, 40.0))
    np.testing.assert_allclose(turned_light(relit.config),
                               turned_light(want), atol=1e-8)
    assert (relit.samples > 0).sum() > 1000
    before, after = (read_exr(tmp_path / f"{n}.exr")["RGB"] for n in ("before", "after"))
    mask = before.max(axis=-1) > 0
    changed = mask != (after.max(axis=-1) > 0)  # black in one picture only
    assert mask.mean() > 0.05 and changed.sum() <= 0.001 * mask.sum(), changed.sum()
    assert not (changed & ~_beside_background(mask)).any()  # at most a speck on the outline
    assert np.abs(after[mask] - before[mask]).mean() > 0.02 * before[mask].mean()


def _beside_background(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of the (H, W) `mask` with a pixel outside it among their
    4 neighbours, and those outside it."""
    outside = np.pad(~mask, 1, constant_values=True)
    return (outside[1:-1, 1:-1] | outside[:-2, 1:-1] | outside[2:, 1:-1]
            | outside[1:-1, :-2] | outside[1:-1, 2:])


def test_a_turned_light_carries_over_when_the_bake_plans_again():
    """A turned sun, then an isovalue outside the lazy bake's range: the bake plans again
    for it under the turned sun (its config keeps the turn), and the new surface shows
    that sun's bake — a bake from scratch under it, to rounding."""
    from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.lazy import view_iso_range

    vol = volumes.load("synthetic:shells:24")
    config = BakeConfig(samples=4, bounces=1, env=SUN)
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    meta = lattice_meta(vol, config)
    shared = SharedLattice.create(geometry, meta["channels"], meta)
    link = BakeLink(vol, config, shared, 2, 0.3, follow_iso=True)
    baked, turned = tuple(turned_light(config)), tuple(_unit((0.2, -0.7, 0.6)))

    def finished(iso):
        p = link.progress
        return lambda: p is not None and p.stage is None and p.iso == iso

    def done(iso):
        def check():
            p = link.progress
            return (p is not None and p.stage is None and p.iso == iso
                    and link.relit_fraction(turned) == 1.0)
        return check

    try:
        deadline = time.monotonic() + 120
        link.send_view(View(0.3, EYE, None, baked))
        _wait(link, lambda: finished(0.3)(), deadline, "the first bake")
        link.send_view(View(0.3, EYE, None, turned))
        _wait(link, done(0.3), deadline, "the re-bake")
        link.send_view(View(0.6, EYE, None, turned))
        _wait(link, lambda: link.replans == 1 and done(0.6)(), deadline, "the new plan")
        relit = relit_config(dataclasses.replace(config, iso_range=view_iso_range(vol, 0.6)),
                             turned)
        assert link.relit_config == relit
        assert link.relit["surface_done"] == link.relit["surface"] > 0
        scratch = Baker(vol, relit, workers=2)
        try:
            cells = cell_index(scratch.plan, geometry.shape)
            surface = surface_positions(scratch.plan, cells, 0.6)
            scratch.run(surface, config.samples)
        finally:
            scratch.close()
        ids = scratch.plan.ids[surface]
        assert shared.relit.reshape(-1)[ids].all()
        np.testing.assert_allclose(shared.lattice.values.reshape(-1, 3)[ids],
                                   scratch.lattice.values.reshape(-1, 3)[ids], rtol=1e-5,
                                   atol=1e-6)
    finally:
        link.stop()
        shared.close()
