"""The first picture: the camera frames the isosurface in the free part of the window, and
automatic exposure brings the surface to middle grey."""

import itertools
from pathlib import Path

import numpy as np
import pytest

from isolume import volumes
from isolume.app.render.camera import FRAME_FILL, Camera, frame_points
from isolume.app.render.exposure import (
    EXPOSURE_KEY,
    auto_exposure_scale,
    quantile,
    weighted_quantile,
)


def _ndc(camera: Camera, aspect: float, points) -> np.ndarray:
    """(N, 2) normalised device coordinates of (N, 3) world points."""
    p = np.c_[np.asarray(points, np.float64), np.ones(len(points))] @ camera.view_proj(
        aspect).T
    return p[:, :2] / p[:, 3:]


@pytest.mark.parametrize(("aspect", "free"), [(1.0, (0.0, 1.0)), (4 / 3, (0.35, 1.0)),
                                              (0.6, (0.2, 0.9))])
@pytest.mark.parametrize("view", [(30.0, 30.0), (200.0, -60.0)])
def test_the_box_fills_the_free_part_and_sits_in_its_middle(aspect, free, view):
    lo, hi = np.array([5.0, -2.0, 10.0]), np.array([9.0, 6.0, 11.0])
    corners = _corners(lo, hi)
    camera = frame_points(Camera(azimuth=view[0], elevation=view[1]), corners, aspect, free)
    centre = _ndc(camera, aspect, [(lo + hi) / 2])[0]
    left, right = 2 * np.asarray(free) - 1
    assert centre == pytest.approx(((left + right) / 2, 0.0), abs=1e-9)
    # the corners stay inside the free part and fill FRAME_FILL of it one way
    ndc = _ndc(camera, aspect, corners)
    middle = (left + right) / 2
    fill = max(np.abs(ndc[:, 0] - middle).max() / ((right - left) / 2),
               np.abs(ndc[:, 1]).max())
    assert fill == pytest.approx(FRAME_FILL, abs=2e-3)
    # the near and far planes enclose the box
    near, far = camera.clip_range()
    eye = camera.eye
    depth = (corners - eye) @ (camera.center - eye) / np.linalg.norm(camera.center - eye)
    assert near < depth.min() and depth.max() < far


def _corners(lo, hi) -> np.ndarray:
    """(8, 3) corners of the box `lo`..`hi`."""
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])])


@pytest.mark.parametrize(("aspect", "free"), [(1.0, (0.0, 1.0)), (4 / 3, (0.35, 1.0)),
                                              (0.6, (0.2, 0.9))])
def test_centred_framing_puts_the_extent_of_the_points_in_the_middle(aspect, free):
    """A lopsided cloud: its projections' extent, not its box centre, sits in the middle
    of the free part and fills FRAME_FILL of it one way."""
    rng = np.random.default_rng(1)
    points = np.r_[rng.normal(0, 1, (500, 3)), [[6.0, 0, 0], [0, 0, 4.0]]]
    camera = frame_points(Camera(azimuth=20, elevation=35), points, aspect, free, centre=True)
    ndc = _ndc(camera, aspect, points)
    left, right = 2 * np.asarray(free) - 1
    low, high = ndc.min(axis=0), ndc.max(axis=0)
    assert (low + high) / 2 == pytest.approx(((left + right) / 2, 0.0), abs=2e-3)
    fill = max((high[0] - low[0]) / (right - left), (high[1] - low[1]) / 2)
    assert fill == pytest.approx(FRAME_FILL, abs=2e-3)


def test_orbiting_keeps_the_target_where_it_was_framed():
    lo, hi = np.zeros(3), np.ones(3)
    camera = frame_points(Camera(), _corners(lo, hi), 1.5, (0.3, 1.0))
    from dataclasses import replace

    for az, el in [(0, 0), (120, 45), (300, -80)]:
        turned = replace(camera, azimuth=az, elevation=el)
        x, y = _ndc(turned, 1.5, [(lo + hi) / 2])[0]
        assert (x, y) == pytest.approx((0.3, 0.0), abs=1e-9)


def test_auto_exposure_without_weights_is_the_weighted_one_of_unit_weights():
    """Without weights the meter partitions instead of sorting (`exposure.quantile`): the
    same exposure, to the bit, as weights of 1 give through `weighted_quantile` and the
    weighted average — over sizes whose bright quantile's rank rounds either way, with
    dark, negative and NaN pixels."""
    rng = np.random.default_rng(5)
    for n in (1, 2, 19, 20, 21, 400, 10_001):
        rgb = rng.lognormal(0, 2, (n, 3)) * (rng.random((n, 1)) > 0.1)
        rgb[::7, 1] = -1.0
        rgb[::11, 0] = np.nan
        mask = rng.random(n) > 0.2
        values = rgb[:, 1][rgb[:, 1] > 0]
        for q in (0.0, 0.5, 0.95, 1.0) if len(values) else ():
            assert quantile(values, q) == weighted_quantile(values, np.ones(len(values)), q)
        assert auto_exposure_scale(rgb, mask) == auto_exposure_scale(rgb, mask,
                                                                     weights=np.ones(n))


def test_auto_exposure_is_the_key_over_the_log_average():
    rgb = np.zeros((4, 4, 3))
    mask = np.zeros((4, 4), bool)
    rgb[:2] = 0.5  # luminance 0.5 on 8 pixels, 2.0 on 4, background ignored
    rgb[2, :] = 2.0
    rgb[3, :] = 1e6
    mask[:3] = True
    expected = EXPOSURE_KEY / np.exp((8 * np.log(0.5) + 4 * np.log(2.0)) / 12)
    assert auto_exposure_scale(rgb, mask) == pytest.approx(expected)
    assert auto_exposure_scale(rgb, np.zeros_like(mask)) == 1.0
    assert auto_exposure_scale(np.zeros_like(rgb), mask) == 1.0  # all black: no opinion
    weights = np.where(np.arange(4)[:, None] < 2, 1.0, 3.0) * np.ones((4, 4))
    heavy = EXPOSURE_KEY / np.exp((8 * np.log(0.5) + 12 * np.log(2.0)) / 20)
    assert auto_exposure_scale(rgb, mask, weights=weights) == pytest.approx(heavy)


def test_auto_exposure_meters_the_lit_pixels_of_a_mostly_unlit_surface():
    """Most of the surface black, a few pixels lit, one nearly black, some NaN: the lit
    pixels alone set the exposure."""
    lum = np.zeros(1000)
    lum[:30] = 1.0
    lum[30:40] = 1e-9
    lum[40:60] = np.nan
    rgb = np.repeat(lum[:, None], 3, axis=1)
    mask = np.ones(1000, bool)
    assert auto_exposure_scale(rgb, mask) == pytest.approx(EXPOSURE_KEY)


@pytest.mark.parametrize("dark", [0.0, 1e-4])
def test_auto_exposure_is_not_fooled_by_a_dark_half(dark):
    """A surface half black (or in deep shadow below 2 % of its bright pixels) is exposed
    as its lit half alone would be: the dark half carries no exposure information. The
    log-average over every pixel would expose it 1/√dark times brighter (the lit half
    blown out white)."""
    rng = np.random.default_rng(3)
    lit = rng.uniform(0.2, 0.8, (64, 64))
    rgb = np.repeat(lit[..., None], 3, axis=2)
    mask = np.ones((64, 64), bool)
    alone = auto_exposure_scale(rgb, mask)
    rgb[:, :32] = dark
    assert auto_exposure_scale(rgb[:, 32:], mask[:, 32:]) == pytest.approx(
        auto_exposure_scale(rgb, mask))
    assert auto_exposure_scale(rgb, mask) == pytest.approx(alone, rel=0.1)
    # a dim but lit gradient (above 2 % of the bright pixels) is metered, not dropped
    rgb[:, :32] = 0.05
    dim = auto_exposure_scale(rgb, mask)
    assert dim > 1.5 * alone


def test_viewer_exposure_adapts_smoothly_in_stops():
    from isolume.app.viewer.draw import EXPOSURE_ADAPT_S, adapted_exposure

    assert adapted_exposure(1.0, 4.0, 0.0) == 1.0
    half = EXPOSURE_ADAPT_S * np.log(2)
    assert adapted_exposure(1.0, 4.0, half) == pytest.approx(2.0)  # half of two stops
    # steps of any size land where one step of their sum lands: no frame-rate dependence
    a = 1.0
    for _ in range(10):
        a = adapted_exposure(a, 0.1, 0.03)
    assert a == pytest.approx(adapted_exposure(1.0, 0.1, 0.3))
    path = [adapted_exposure(1.0, 0.1, t) for t in np.linspace(0, 3, 30)]
    assert all(0.1 < b < a <= 1.0 for a, b in itertools.pairwise(path))  # no overshoot


# -- the surface's points and the camera of render, reference and movie ------------------------
def test_level_points_are_the_marching_cubes_vertices():
    vol = volumes.load("synthetic:engine:48")
    for iso in vol.suggested_iso:
        mesh = volumes.isosurface(vol, iso, normals="none", keep_degenerate=True)
        points = volumes.level_points(vol, iso)
        assert len(points) == len(mesh.vertices)
        np.testing.assert_allclose(points.min(axis=0), mesh.vertices.min(axis=0), atol=1e-5)
        np.testing.assert_allclose(points.max(axis=0), mesh.vertices.max(axis=0), atol=1e-5)


def test_level_points_of_a_range_and_under_a_limit():
    vol = volumes.load("synthetic:sphere:32")
    both = volumes.level_points(vol, 0.3, 0.7)
    for iso in (0.3, 0.7):
        one = volumes.level_points(vol, iso)
        assert (both.min(axis=0) <= one.min(axis=0)).all()
        assert (both.max(axis=0) >= one.max(axis=0)).all()
    full = volumes.level_points(vol, 0.5)
    few = volumes.level_points(vol, 0.5, limit=500)
    assert 250 <= len(few) <= 500
    np.testing.assert_array_equal(few, volumes.level_points(vol, 0.5, limit=500))
    voxel = max(vol.spacing)
    np.testing.assert_allclose(few.min(axis=0), full.min(axis=0), atol=2 * voxel)
    np.testing.assert_allclose(few.max(axis=0), full.max(axis=0), atol=2 * voxel)
    assert len(volumes.level_points(vol, vol.value_range[1] + 1)) == 0


def _numpy_crossings(layers, axis, lo, hi):
    """The crossings `cubes.edge_crossings` finds, by numpy: (L, N, 3)."""
    n = layers.shape[axis] - 1
    a = np.take(layers, np.arange(n), axis=axis)
    b = np.take(layers, np.arange(1, n + 1), axis=axis)
    index = np.nonzero((np.minimum(a, b) <= hi) & (np.maximum(a, b) >= lo) & (a != b))
    a, b = a[index].astype(np.float64), b[index].astype(np.float64)
    coords = np.stack(index, axis=1).astype(np.float64)
    ends = []
    for level in (lo,) if lo == hi else (lo, hi):
        at = coords.copy()
        at[:, axis] += (np.clip(level, np.minimum(a, b), np.maximum(a, b)) - a) / (b - a)
        ends.append(at)
    return np.stack(ends)


@pytest.mark.parametrize("dtype", [np.uint8, np.int8, np.uint16, np.int16, np.float32])
def test_edge_crossings_match_numpy_to_the_bit(dtype):
    """The compiled crossing points of `level_points` are numpy's, in numpy's order, for
    integer and float samples, one level and a range, edges equal to a level included
    (float32 samples compared in float32, as numpy compares them with a Python float)."""
    from isolume.volumes.mesh import _slab_crossings

    gen = np.random.default_rng(4)
    centre, spread = {np.int8: (0, 40), np.float32: (0.5, 0.2)}.get(dtype, (100, 40))
    values = gen.normal(centre, spread, (37, 9, 11))
    if dtype != np.float32:
        values = np.clip(np.round(values), np.iinfo(dtype).min, np.iinfo(dtype).max)
    data = values.astype(dtype)
    level = float(data.flat[17])
    if dtype == np.float32:  # float32(0.1) > 0.1: numpy's float32 comparison counts it
        data.flat[::7], level = np.float32(0.1), 0.1
    between = float(np.percentile(data, 30)) + (0.25 if dtype != np.float32 else 0.0)
    for lo, hi in [(level, level), (between, float(np.percentile(data, 60)))]:
        slabs = _slab_crossings(data, [0, 32], lo, hi)
        for k0, parts in zip([0, 32], slabs, strict=True):
            k1 = min(k0 + 32, data.shape[0] - 1)
            layers = data[k0:k1 + 1] if k1 == data.shape[0] - 1 else data[k0:k1]
            for got, (part, axis) in zip(parts, [(data[k0:k1 + 1], 0), (layers, 1),
                                                 (layers, 2)], strict=True):
                want = _numpy_crossings(part, axis, lo, hi).reshape(-1, 3)
                assert len(want) > 0
                np.testing.assert_array_equal(got, want)


def test_level_points_are_the_same_on_any_number_of_threads():
    """Thinned to a limit, the points do not depend on the threads that found them."""
    from isolume.volumes import cores

    vol = volumes.load("synthetic:engine:64")
    got = []
    for threads in (1, 3):
        cores.use(threads)
        try:
            got.append(volumes.level_points(vol, 0.3, 0.5, limit=3000))
        finally:
            cores.use(None)
    assert len(got[0]) == 3000
    np.testing.assert_array_equal(got[0], got[1])


@pytest.fixture(scope="module")
def small_ball(tmp_path_factory) -> Path:
    """A .npy volume: a ball of radius 5 voxels in a corner of a 48³ box."""
    z, y, x = np.mgrid[:48, :48, :48].astype(np.float32)
    field = 8.0 - np.sqrt((x - 12) ** 2 + (y - 10) ** 2 + (z - 34) ** 2)
    path = tmp_path_factory.mktemp("ball") / "ball.npy"
    np.save(path, np.clip(field, 0, 8).astype(np.float32))
    return path


def _extent(mask: np.ndarray) -> tuple[float, float, float, float]:
    """(width, height) of the mask's extent as fractions of the picture, and its centre
    (x, y) in pixels from the picture's middle."""
    rows, cols = np.nonzero(mask)
    h, w = mask.shape
    return ((np.ptp(cols) + 1) / w, (np.ptp(rows) + 1) / h,
            (cols.min() + cols.max() + 1) / 2 - w / 2, (rows.min() + rows.max() + 1) / 2 - h / 2)


def test_render_and_reference_frame_a_small_object_in_the_middle(small_ball, tmp_path, capsys):
    """`render` and `reference` frame the surface, not its volume's box: the ball fills
    FRAME_FILL of the picture one way, in the middle, and both see the same pixels."""
    from isolume.app.cli import main
    from isolume.app.render.images import read_exr

    common = [str(small_ball), "--iso", "3", "--size", "64x48"]
    assert main(["render", *common, "--shading", "lambert", "--gl", "osmesa",
                 "--out", str(tmp_path / "r.exr")]) == 0
    assert main(["reference", *common, "--spp", "1", "--bounces", "0",
                 "--out", str(tmp_path / "ref.exr")]) == 0
    capsys.readouterr()
    rendered = read_exr(tmp_path / "r.exr")["RGB"].max(axis=-1) > 0
    traced = read_exr(tmp_path / "ref.exr")["mask"] > 0
    width, height, dx, dy = _extent(rendered)
    assert max(width, height) >= FRAME_FILL - 2 / 48 and min(width, height) > 0.5
    assert abs(dx) <= 1 and abs(dy) <= 1
    assert (rendered != traced).mean() < 0.02  # outline pixels only
