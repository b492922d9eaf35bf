"""Paths where a picture's noise is (`baking.view_paths`): the allocation, the picture's
share of each texel and the neighbourhood means against independent implementations, and
the traced light against a uniform pass of the same budget and a 1024-path reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from isolume import volumes
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import LUMINANCE, TRAPPED_PATHS, LatticeGeometry, trilinear_corners
from isolume.baking.preview import (
    SeenSurface,
    estimate,
    nearest_points,
    preview_tracing,
    surface_scene,
)
from isolume.baking.view_paths import (
    PILOT,
    allocate,
    neighbour_mean,
    noise_placed,
    picture_share,
)
from isolume.baking.view_texels import HeldLattice


def test_allocate_spends_the_budget_in_proportion_to_the_weights():
    counts = allocate(np.array([1.0, 3.0]), 40, 8, 512)
    assert counts.tolist() == [10, 30]
    weights = np.random.default_rng(0).lognormal(0.0, 2.0, 10_000)
    counts = allocate(weights, 32 * len(weights), 8, 256)
    assert counts.sum() <= 32 * len(weights)
    free = (counts > 8) & (counts < 256)  # neither clamp holds: ⌊c w⌋, one c for all
    c = counts[free] / weights[free]
    assert np.all(np.floor(c.max() * weights[free]) <= counts[free] + 1)
    assert 32 * len(weights) - counts.sum() < free.sum()  # ⌊⌋ leaves less than 1 a texel
    assert counts.min() == 8 and counts.max() == 256


def test_allocate_keeps_the_least_for_texels_of_no_weight_and_caps_the_rest():
    assert allocate(np.zeros(3), 100, 8, 64).tolist() == [8, 8, 8]
    assert allocate(np.array([0.0, 1.0, 1.0]), 1000, 8, 64).tolist() == [8, 64, 64]
    assert allocate(np.array([1.0, 1e-9]), 16, 8, 64).tolist() == [8, 8]


def test_picture_share_sums_the_squared_weights_of_trilinear_corners():
    geometry = LatticeGeometry((9, 7, 5), (0.0, 0.0, 0.0), (5.0, 7.0, 9.0))
    rng = np.random.default_rng(1)
    points = rng.uniform(-1.0, 10.0, (500, 3))  # some beyond the box: clamped as GL does
    corners, weights = trilinear_corners(geometry.shape, geometry.to_texel_coords(points))
    flat = np.ravel_multi_index(tuple(corners.reshape(-1, 3).T), geometry.shape)
    texels = np.unique(flat)[::2]  # a texel the lookups read but not held gets nothing
    want = np.zeros(len(texels))
    for f, w in zip(flat, weights.reshape(-1), strict=True):
        row = np.searchsorted(texels, f)
        if row < len(texels) and texels[row] == f:
            want[row] += w * w
    np.testing.assert_allclose(picture_share(geometry, texels, points), want, rtol=1e-12)


def test_neighbour_mean_averages_over_the_texels_held_around_each():
    shape = (6, 7, 8)
    rng = np.random.default_rng(2)
    texels = np.sort(rng.choice(np.prod(shape), 150, replace=False))
    values = rng.random(len(texels))
    held = dict(zip(texels.tolist(), values, strict=True))
    want = []
    for z, y, x in zip(*np.unravel_index(texels, shape), strict=True):
        around = [held[f] for k in (z - 1, z, z + 1) for j in (y - 1, y, y + 1)
                  for i in (x - 1, x, x + 1)
                  if 0 <= k < shape[0] and 0 <= j < shape[1] and 0 <= i < shape[2]
                  and (f := (k * shape[1] + j) * shape[2] + i) in held]
        want.append(np.mean(around))
    np.testing.assert_allclose(neighbour_mean(shape, texels, values), want, rtol=1e-12)


@pytest.fixture(scope="module")
def contact():
    """A sphere just above a plane under a sky and a sun (its direct light in the pixels):
    open sky, a shadow and a contact gap, whose light spreads far more than the open
    plane's. The mesh's vertices stand for a picture's pixels."""
    vol = volumes.load("synthetic:contact")
    mesh = volumes.isosurface(vol, 0.5)
    config = BakeConfig(env="sky:sun=4,sun_az=30,sun_el=35", direct_light="pixels",
                        samples=32)
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    texels, nearest = nearest_points(geometry, mesh.vertices)
    offset = config.offset * float(np.mean(vol.spacing))
    seen = SeenSurface(mesh.vertices, mesh.vertices + offset * mesh.normals, mesh.normals,
                       texels, nearest)
    share = picture_share(geometry, texels, mesh.vertices)
    return vol, config, texels, seen, surface_scene(vol, 0.5, 1), share


def _light(contact, paths, share, seed=0, workers=2, stratified=True):
    """(K,) luminance and (K,) paths of the contact scene's texels (`stratified`: the
    previews' first directions, else drawn from the paths' keys as a bake's are)."""
    vol, config, texels, seen, scene, _ = contact
    config = dataclasses.replace(config, seed=seed)
    lattice = HeldLattice.for_texels(vol, config, texels)
    tracing = dataclasses.replace(preview_tracing(vol, config), stratified=stratified)
    estimate(vol, config, lattice, 0.5, texels, scene, 1, paths=paths,
             tracing=tracing, workers=workers, seen=seen, share=share)
    return lattice.values @ LUMINANCE, lattice.paths.astype(np.int64)


def test_stratified_first_directions_lower_the_pictures_error(contact):
    """The same 32 paths at every texel, their first directions stratified over each
    texel's samples (the previews' and views' `Tracing.stratified`) or drawn from the
    paths' keys as a bake's are: the picture's squared error against a 1024-path
    reference (each texel's weighed by its share of the pixels) measured 0.76–0.82 of the
    independent paths' over seeds 0–3 — the sky's visibility and the first bounce's hit
    points are sampled evenly, the sun-lit bounces after them are not. Each sum runs over
    ~10⁴ texels, so it varies by a few per cent between seeds; 0.9 leaves room. The
    picture's mean agrees with the reference's within 5 standard errors of its own
    (estimated from the independent paths' errors): stratifying shifts no light."""
    share = contact[-1]
    reference, _ = _light(contact, 1024, None, seed=99, stratified=False)
    for seed in (0, 1):
        plain, _ = _light(contact, 32, None, seed, stratified=False)
        even, _ = _light(contact, 32, None, seed)
        ratio = (share * (even - reference) ** 2).sum() / (share * (plain - reference) ** 2).sum()
        assert ratio < 0.9, ratio
        standard_error = np.sqrt((share**2 * (plain - reference) ** 2).sum())
        assert abs((share * (even - reference)).sum()) < 5 * standard_error


def test_paths_placed_by_noise_halve_the_pictures_squared_error(contact):
    """At 32 paths a texel, placed by noise or the same at every texel, the picture's
    squared error against a 1024-path reference (each texel's weighed by its share of the
    pixels, what the picture shows): measured 0.47–0.51 of the even paths' over seeds
    0–2. Each sum runs over ~10⁴ texels whose errors are independent, so it varies by a
    few per cent between seeds; 0.7 leaves room for ten times that. The reference's own
    noise adds 1/32 of either error, as much to both."""
    share = contact[-1]
    reference, _ = _light(contact, 1024, None, seed=99)
    for seed in (0, 1):
        even, even_paths = _light(contact, 32, None, seed)
        noise, noise_paths = _light(contact, 32, share, seed)
        assert noise_paths.sum() <= even_paths.sum() == 32 * np.count_nonzero(even_paths)
        assert noise_paths.min() >= 0 and noise_paths.max() > 4 * 32  # the gap gets many
        ratio = (share * (noise - reference) ** 2).sum() / (share * (even - reference) ** 2).sum()
        assert ratio < 0.7, ratio


def test_paths_placed_by_noise_are_the_same_bits_on_any_number_of_threads(contact):
    share = contact[-1]
    one, one_paths = _light(contact, 32, share, workers=1)
    two, two_paths = _light(contact, 32, share, workers=2)
    assert np.array_equal(one_paths, two_paths) and np.array_equal(one, two)


def test_texels_dark_on_their_paths_go_on_to_the_trapped_count():
    """Paths that start inside a closed sphere never reach the sky: those texels are
    traced on to `TRAPPED_PATHS` (known trapped, left out of the lookups, where fewer
    paths would draw them black); texels outside keep the budget's share."""
    vol = volumes.load("synthetic:sphere:32")
    config = BakeConfig(env="constant:1", bounces=1, samples=16)
    scene = surface_scene(vol, 0.5, 1)
    centre = np.asarray(vol.box[0] + vol.box[1], np.float32) / 2
    ids = np.arange(200, dtype=np.int64)
    inside = ids % 2 == 0
    far = np.asarray(vol.box[1], np.float32) * 3  # open sky all round
    origins = np.where(inside[:, None], centre, far).astype(np.float32)
    normals = np.tile(np.float32([0.0, 0.0, 1.0]), (len(ids), 1))
    tracing = dataclasses.replace(preview_tracing(vol, config), ids=ids)
    sums, count = noise_placed(scene, tracing, origins, normals, (100, 2, 1), np.ones(len(ids)),
                               16, TRAPPED_PATHS, workers=2)
    assert not sums[inside].any() and (count[inside] == TRAPPED_PATHS).all()
    assert sums[~inside].all() and (count[~inside] >= PILOT).all()
    assert count[~inside].max() <= 8 * 16


def test_a_views_lattice_spreads_its_paths_as_asked(contact):
    """`view_lattice(spread=...)`: "even" gives every texel `samples` paths, "noise" the
    same paths in all, placed unevenly, and more only for the texels dark on theirs (on
    to `TRAPPED_PATHS`); anything else is refused."""
    from isolume.app.render.view_gi import view_lattice

    vol, config, _, seen, scene, _ = contact
    eye = np.asarray(vol.box[1], np.float64) * 4
    even = view_lattice(vol, config, 0.5, seen.points, eye, workers=2, progress=False,
                        scene=scene, spread="even")
    noise = view_lattice(vol, config, 0.5, seen.points, eye, workers=2, progress=False,
                         scene=scene)
    traced = even.paths > 0
    assert traced.any() and (even.paths[traced] == config.samples).all()
    assert np.array_equal(noise.paths > 0, traced)
    dark = noise.paths == TRAPPED_PATHS
    assert noise.paths.sum() - even.paths.sum() <= TRAPPED_PATHS * dark.sum()
    assert len(np.unique(noise.paths)) > 10
    with pytest.raises(ValueError, match="spread 'flat'"):
        view_lattice(vol, config, 0.5, seen.points, eye, scene=scene, spread="flat")
