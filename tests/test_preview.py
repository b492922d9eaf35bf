"""First estimates on the displayed surface (`baking.preview`) and how they are shown."""

from dataclasses import replace

import numpy as np
import pytest

from isolume import volumes
from isolume.baking.bake import Baker
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.lazy import visible_cells
from isolume.baking.passes import MIN_PATHS_PER_CHUNK
from isolume.baking.preview import (
    FIRST_PASS_PATHS,
    Previewer,
    cell_corners,
    estimate,
    first_pass_paths,
    mesh_step,
    pass_plan,
    preview_tracing,
    surface_scene,
)


@pytest.fixture(scope="module")
def sphere():
    vol = volumes.load("synthetic:sphere:32")
    mesh = volumes.isosurface(vol, 0.5)
    return vol, mesh


def _empty(vol, config):
    geometry = LatticeGeometry.for_volume(vol, config.scale)
    lat = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    lat.preview = np.zeros_like(lat.values)
    lat.preview_paths = np.zeros(geometry.shape, np.uint16)
    return lat


def _preview_all(vol, config, lat, iso, cells, workers=1):
    """Every preview pass of one view; returns the flat ids written by each."""
    previewer = Previewer(vol, config, lat, workers)
    written = [previewer.set_view(iso, cells)]
    while previewer.busy:
        written.append(previewer.step())
    return written, previewer


def test_cell_corners_are_the_eight_corners():
    shape = (3, 4, 5)
    corners = cell_corners(shape, np.array([0, 1 * 20 + 2 * 5 + 3]))
    k, j, i = np.unravel_index(corners, shape)
    got = set(zip(k.tolist(), j.tolist(), i.tolist(), strict=True))
    want = {(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)}
    want |= {(1 + a, 2 + b, 3 + c) for a in (0, 1) for b in (0, 1) for c in (0, 1)}
    assert got == want


def test_pass_plan_grows_and_stops_at_the_bake_samples():
    assert pass_plan(1000) == [(4, True), (64, False), (256, False)]
    assert pass_plan(100) == [(4, True), (64, False), (100, False)]
    assert pass_plan(4) == [(4, True)]
    assert pass_plan(2) == [(2, True)]


def test_a_first_pass_over_many_texels_takes_fewer_paths_each():
    assert first_pass_paths(4, 1000) == 4
    assert first_pass_paths(4, FIRST_PASS_PATHS // 4) == 4
    assert first_pass_paths(4, FIRST_PASS_PATHS // 2) == 2
    assert first_pass_paths(4, FIRST_PASS_PATHS) == 1
    assert first_pass_paths(4, 100 * FIRST_PASS_PATHS) == 1


def test_a_view_of_many_texels_gets_one_path_each_first_then_the_full_passes(sphere,
                                                                            monkeypatch):
    """Over the budget, the first pass traces one path per texel and says so in its path
    counts; the next pass still brings every texel to its own count. A scene prepared
    for the isovalue beforehand is the one the first pass traces."""
    vol, mesh = sphere
    config = BakeConfig(env="constant:1", bounces=0, samples=16)
    lat = _empty(vol, config)
    cells = visible_cells(lat.geometry, mesh.vertices)
    texels = len(cell_corners(lat.geometry.shape, cells))
    monkeypatch.setattr("isolume.baking.preview.FIRST_PASS_PATHS", texels)
    previewer = Previewer(vol, config, lat)
    previewer.prepare(0.5)
    prepared = dict(previewer._scenes)
    assert len(prepared) == 1
    first = previewer.set_view(0.5, cells)
    assert previewer._scenes == prepared  # not made again
    assert len(first) == texels and (lat.preview_paths.reshape(-1)[first] == 1).all()
    while previewer.busy:
        previewer.step()
    assert [(d["paths"], d["texels"]) for d in previewer.done] == [(1, texels), (16, texels)]
    assert (lat.preview_paths.reshape(-1)[first] == 16).all()


@pytest.mark.parametrize("first_step", [1, 2, 4])
def test_previews_on_a_convex_surface_under_a_uniform_sky_are_exact(sphere, first_step,
                                                                    monkeypatch):
    """Unoccluded convex surface, constant sky L: every path returns πL (cosine sampling
    is the zero-variance estimator), so every pass's previews equal πL exactly: the
    offset causes no self-shadowing, on the full surface and on the step-2 and step-4
    ones of large volumes (the first pass's)."""
    vol, mesh = sphere
    coarse_voxels = {1: vol.data.size, 2: vol.data.size - 1, 4: 0}[first_step]
    monkeypatch.setattr("isolume.baking.preview.COARSE_VOXELS", coarse_voxels)
    assert mesh_step(vol, True) == first_step
    config = BakeConfig(env="constant:0.5,1,2", bounces=1, samples=16)
    lat = _empty(vol, config)
    cells = visible_cells(lat.geometry, mesh.vertices)
    previewer = Previewer(vol, config, lat, workers=2)
    first = previewer.set_view(0.5, cells)
    assert len(first) == len(cell_corners(lat.geometry.shape, cells))
    assert (lat.preview_paths.reshape(-1)[first] == 4).all() and previewer.busy
    while previewer.busy:
        previewer.step()
    values = lat.preview.reshape(-1, 3)[first]
    np.testing.assert_allclose(values, np.broadcast_to(np.pi * np.array([0.5, 1, 2]), values.shape),
                               rtol=1e-5)
    assert (lat.samples == 0).all()  # nothing counted as a sample
    assert (lat.preview_paths.reshape(-1)[first] == 16).all()
    assert lat.shown().sum() == len(first) == lat.previewed().sum()
    assert [(d["paths"], d["texels"]) for d in previewer.done] == [(4, len(first)),
                                                                    (16, len(first))]


def test_a_view_is_previewed_once_per_isovalue(sphere):
    """The same isovalue seen again costs nothing; another one redoes the previews."""
    vol, mesh = sphere
    config = BakeConfig(env="constant:1", bounces=0, samples=8)
    lat = _empty(vol, config)
    cells = visible_cells(lat.geometry, mesh.vertices)
    written, previewer = _preview_all(vol, config, lat, 0.5, cells)
    assert all(len(w) for w in written)
    assert len(previewer.set_view(0.5, cells)) == 0 and not len(previewer.step())
    assert len(previewer.set_view(0.45, cells)) > 0


def test_texels_with_enough_samples_of_their_own_get_no_preview(sphere):
    vol, mesh = sphere
    config = BakeConfig(env="constant:1", bounces=0, samples=16)
    lat = _empty(vol, config)
    cells = visible_cells(lat.geometry, mesh.vertices)
    corners = cell_corners(lat.geometry.shape, cells)
    done, some = corners[::3], corners[1::3]
    lat.samples.reshape(-1)[done] = 16
    lat.samples.reshape(-1)[some] = 8
    lat.values.reshape(-1, 3)[np.concatenate([done, some])] = 42.0
    written, _ = _preview_all(vol, config, lat, 0.5, cells)
    assert not np.isin(done, np.concatenate(written)).any()
    assert not lat.preview_paths.reshape(-1)[done].any()
    # 8 own samples: previewed at 4 paths no, at 16 yes — and shown until the bake has 16
    assert not np.isin(some, written[0]).any() and np.isin(some, written[1]).all()
    shown = lat.displayed().reshape(-1, 3)
    assert (shown[done] == 42.0).all() and (shown[some] != 42.0).all()
    lat.samples.reshape(-1)[some] = 16
    assert (lat.displayed().reshape(-1, 3)[some] == 42.0).all()


def test_previews_agree_with_the_bake_where_the_surface_is_one_level():
    """Shells under a sky with the sun: where a texel's own isovalue is the displayed
    one the two estimates differ by Monte Carlo noise only. With 16 paths per preview
    and 64 per bake the mean relative difference over hundreds of texels is noise of
    ~1 %; the bound (4 %) catches a wrong scene (the step-2 mesh of this small volume:
    11 %), a wrong normal or a missing factor."""
    vol = volumes.load("synthetic:shells:32")
    iso = vol.suggested_iso[0] if isinstance(vol.suggested_iso, tuple) else vol.suggested_iso
    config = BakeConfig(env="sky:sun=2", bounces=1, samples=16, direct_light="lattice")
    lat = _empty(vol, config)
    mesh = volumes.isosurface(vol, iso)
    cells = visible_cells(lat.geometry, mesh.vertices)
    written, _ = _preview_all(vol, config, lat, iso, cells, workers=2)
    flat = written[0]
    previewed = lat.preview_paths.reshape(-1)[flat] == 16  # the rest would start inside
    assert previewed.mean() > 0.97
    flat = flat[previewed]
    first = lat.preview.reshape(-1, 3)[flat].copy()
    baker = Baker(vol, replace(config, samples=64), workers=2)
    try:
        ids = baker.plan.ids
        pos = np.minimum(np.searchsorted(ids, flat), len(ids) - 1)
        ok = ids[pos] == flat  # active texels only
        rho = baker.plan.rho[pos[ok]]
        near = np.abs(rho - iso) < 0.02 * np.ptp(vol.value_range)
        baker.run(pos[ok][near])
        baked = baker.lattice.values.reshape(-1, 3)[flat[ok][near]]
    finally:
        baker.close()
    assert near.sum() > 50
    lum_first, lum_baked = first[ok][near].mean(axis=1), baked.mean(axis=1)
    assert abs(lum_first.mean() / lum_baked.mean() - 1) < 0.04


def test_nothing_to_do_at_the_data_extreme(sphere):
    vol, mesh = sphere
    config = BakeConfig(env="constant:1")
    lat = _empty(vol, config)
    cells = visible_cells(lat.geometry, mesh.vertices)
    lo, _ = vol.value_range
    written, previewer = _preview_all(vol, config, lat, lo, cells)
    assert sum(len(w) for w in written) == 0 and not previewer.busy
    assert lat.preview_paths.sum() == 0


def test_shown_displayed_sampled_and_saved(tmp_path, sphere):
    """A display shows a preview while it rests on more paths than the texel's own
    samples, and looks it up like any value; a saved copy has no previews."""
    from isolume.app.viewer.bake_client import SharedLattice

    vol, _ = sphere
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    shared = SharedLattice.create(geometry, 3, {"kind": "irradiance"})
    try:
        lat = shared.lattice
        lat.samples[0, 0, 0] = 3
        lat.values[0, 0, 0] = 1.0
        lat.preview_paths[1, 1, 1] = 4
        lat.preview[1, 1, 1] = 2.0
        assert lat.shown().sum() == 2 and lat.previewed().sum() == 1
        assert lat.shown(np.s_[1:2, 1:2, 1:2]).all()
        assert (lat.displayed()[1, 1, 1] == 2.0).all() and (lat.displayed()[0, 0, 0] == 1).all()
        centre = geometry.centres(np.array([np.ravel_multi_index((1, 1, 1), geometry.shape)]))
        np.testing.assert_allclose(lat.sample(centre, normalized=True), [[2.0, 2.0, 2.0]])
        lat.samples[1, 1, 1], lat.values[1, 1, 1] = 4, 5.0  # the bake caught up
        assert (lat.displayed()[1, 1, 1] == 5.0).all()
        copy = shared.snapshot()
        assert copy.preview is None and copy.preview_paths is None
        lat.samples[1, 1, 1] = 0
        assert (shared.snapshot().values[1, 1, 1] == 0).all()
    finally:
        shared.close()


def test_the_bake_process_shows_previews_before_its_plan(tmp_path):
    """The viewer's bake process: the first view's visible texels get previews (no
    samples) in passes of growing path counts, announced as they come; the plan
    withdraws those outside the active set, and the lazy bake's own samples follow."""
    import time

    from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta
    from isolume.baking.lazy import View

    vol = volumes.load("synthetic:sphere:24")
    config = BakeConfig(samples=16, bounces=0, env="constant:1")
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    meta = lattice_meta(vol, config)
    shared = SharedLattice.create(geometry, meta["channels"], meta)
    mesh = volumes.isosurface(vol, 0.5)
    cells = visible_cells(geometry, mesh.vertices[mesh.vertices[:, 1] < 0])  # the front
    link = BakeLink(vol, config, shared, 1, 0.5)
    try:
        link.send_view(View(0.5, (0.0, -2.0, 0.0), cells))
        announced, deadline = [], time.monotonic() + 120
        while not link.previews and time.monotonic() < deadline and link.error is None:
            announced += link.poll()
            time.sleep(0.05)
        assert link.error is None and link.previews
        assert link.previews[0][1]["texels"] == len(cell_corners(geometry.shape, cells))
        while (shared.lattice.samples > 0).sum() == 0 and time.monotonic() < deadline:
            announced += link.poll()
            time.sleep(0.05)
    finally:
        link.stop()
    lat = shared.lattice
    first = lat.preview_paths.reshape(-1) > 0
    assert first.any() and not (first & ~lat.active.reshape(-1)).any()  # inactive withdrawn
    assert np.isin(np.flatnonzero(first), np.concatenate(announced)).all()
    assert [f["paths"] for _, f in link.previews] == [4, 16]
    shared.close()


def test_full_surface_previews_start_on_the_surface_along_the_smoothed_normal(
        sphere, monkeypatch):
    """On the full surface a preview's paths leave from the texel centre moved onto the
    raw field's isosurface (what the mesh shows), offset along the bake's smoothed-gradient
    normal: plain-gradient starts put black marks on the tops of the synthetic engine's
    thin posts, and smoothed-gradient steps alone stall short of the surface (paths
    starting inside the material: 593 of 112 k texels on the engine CT)."""
    import isolume.baking.preview as preview

    vol, mesh = sphere
    config = BakeConfig(env="constant:1", bounces=0, samples=8)
    lat = _empty(vol, config)
    seen = []
    real = preview.trace_counts
    monkeypatch.setattr(preview, "trace_counts", lambda scene, tracing, origins, normals,
                        *rest: seen.append((origins, normals))
                        or real(scene, tracing, origins, normals, *rest))
    _preview_all(vol, config, lat, 0.5, visible_cells(lat.geometry, mesh.vertices))
    origins, normals = seen[-1]  # the last pass: full surface
    h = float(np.mean(vol.spacing))
    on = origins - config.offset * h * normals
    np.testing.assert_allclose(volumes.value_at(vol, on), 0.5, atol=2e-3)  # on the surface
    np.testing.assert_allclose(normals, volumes.normals_at(vol, on, smooth=True), atol=1e-4)


def test_texels_whose_start_is_inside_the_material_get_no_preview(sphere, monkeypatch):
    """A start point on the wrong side of the isosurface (inside the material) would
    bring back black paths: such texels are left without a preview, and the display
    interpolates their neighbours."""
    import isolume.baking.preview as preview

    vol, mesh = sphere
    config = BakeConfig(env="constant:1", bounces=0, samples=4)
    lat = _empty(vol, config)
    cells = visible_cells(lat.geometry, mesh.vertices)
    real = volumes.normals_at
    monkeypatch.setattr(preview.volumes, "normals_at",  # every other normal turned inwards
                        lambda *a, **k: real(*a, **k) * np.where(np.arange(len(a[1])) % 2, -1,
                                                                 1)[:, None])
    written, _ = _preview_all(vol, config, lat, 0.5, cells)
    paths = lat.preview_paths.reshape(-1)[written[0]]
    assert (paths[1::2] == 0).all() and (paths[::2] == 4).all()
    np.testing.assert_allclose(lat.preview.reshape(-1, 3)[written[0][::2]], np.pi, rtol=1e-5)


def test_one_estimate_reports_its_texels_as_they_are_traced_and_keeps_their_bits(sphere):
    """`estimate(..., told=...)` traces all its texels in one call on every core and is
    told the texels done, rising to all of them; each texel's paths are its own, so the
    previews are the same bits as those of estimates of its texels in parts."""
    vol, mesh = sphere
    config = BakeConfig(env="constant:1", bounces=1, samples=8)
    whole, parts = _empty(vol, config), _empty(vol, config)
    flat = cell_corners(whole.geometry.shape, visible_cells(whole.geometry, mesh.vertices))
    scene, tracing = surface_scene(vol, 0.5, 1), preview_tracing(vol, config)
    told = []
    estimate(vol, config, whole, 0.5, flat, scene, 1, paths=64, tracing=tracing, workers=2,
             told=told.append)
    assert len(flat) > 4 * MIN_PATHS_PER_CHUNK // 64  # several work items
    assert len(told) > 2 and told == sorted(told) and told[-1] == len(flat)
    for part in np.array_split(flat, 3):
        estimate(vol, config, parts, 0.5, part, scene, 1, paths=64, tracing=tracing)
    assert np.array_equal(whole.preview_paths, parts.preview_paths)
    assert np.array_equal(whole.preview, parts.preview) and whole.preview.any()
