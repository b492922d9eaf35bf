"""The reference path tracer: analytic answers, the GL renderer, its own statistics.

Tolerances come from known bounds, not from trial: the smoothed-gradient normal at a
mesh point of the 48³ sphere is within 1° of the analytic normal (measured ≤ 0.4°;
test_isosurface bounds it), marching-cubes vertices lie within 0.05 voxel of the sphere,
and a pixel's footprint at the sphere is computed from the camera.
"""

import json
import threading

import numpy as np
import pytest
from scipy import ndimage

from isolume.app.cli import main
from isolume.app.render.camera import Camera
from isolume.app.render.images import read_exr
from isolume.app.render.renderer import default_camera
from isolume.app.render.settings import RenderSettings
from isolume.baking import BakeConfig
from isolume.baking.reference import PixelStats, ReferenceTracer, render_reference
from isolume.volumes.synthetic import SPHERE_RADIUS, make

VIEW = (20.0, 25.0, 1.1)
SIZE = (96, 80)
ALBEDO = (0.5, 0.6, 0.7)
KEY = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
E0 = np.array([2.0, 1.0, 0.5])
MESH_ERROR_VOXELS = 0.05


@pytest.fixture(scope="module")
def sphere():
    """(volume, camera, origins, dirs) of the 48³ sphere seen from VIEW at SIZE."""
    vol = make("sphere", 48)
    camera = default_camera(vol, VIEW)
    origins, dirs = camera.primary_rays(*SIZE)
    return vol, camera, origins, dirs


@pytest.mark.parametrize("smooth", [True, False])
def test_compiled_primary_hits_are_numpys_to_the_bit(smooth):
    """`primary_hits` in compiled blocks (Embree called per ray) against the numpy over
    embreex's batches that it stands in for, on the granular ball, whose grains turn the
    normals to the facets and put facets in the way of some starts (13 of them moved back
    along their rays at the default offset): the same pixels, points, starts and normals,
    bit for bit."""
    from test_shadow_rays import _granular

    from isolume import volumes
    from isolume.baking.reference import primary_hits
    from isolume.baking.trace import Scene

    volume = _granular()
    mesh = volumes.isosurface(volume, 0.5)
    scene = Scene(mesh.vertices, mesh.faces)
    if scene.calls is None:
        pytest.skip("Embree's per-ray calls are not available here")
    origins, dirs = default_camera(volume, (30.0, 30.0, 0.9)).primary_rays(96, 96)
    config = BakeConfig()
    compiled = primary_hits(scene, volume, origins, dirs, config, smooth)
    scene.calls = None
    batched = primary_hits(scene, volume, origins, dirs, config, smooth)
    for name in ("pixels", "points", "origins", "normals"):
        np.testing.assert_array_equal(getattr(compiled, name), getattr(batched, name))
    lift = config.offset * float(np.mean(volume.spacing))
    lifted = compiled.points + lift * compiled.normals
    moved = np.abs(compiled.origins - lifted).max(axis=1) > 1e-9
    assert 0.4 < len(compiled.pixels) / len(dirs) < 0.9 and 0 < moved.sum() < 100


def _ray_sphere(camera: Camera, origins, dirs, radius=SPHERE_RADIUS):
    """Analytic hits of the rays with a sphere about the camera target: (N,) hit, (N, 3)
    unit normals, (N,) cosine between normal and the direction to the eye."""
    oc = origins - np.asarray(camera.target)
    b = (oc * dirs).sum(1)
    disc = b * b - ((oc * oc).sum(1) - radius**2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    normals = (oc + t[:, None] * dirs) / radius
    return hit, normals, -(normals * dirs).sum(1)


def _pixel_size(camera: Camera, height: int) -> float:
    """World size of one pixel at the distance of the sphere's outline."""
    dist = np.linalg.norm(camera.eye - np.asarray(camera.target))
    tangent = np.sqrt(dist**2 - SPHERE_RADIUS**2)
    return 2 * tangent * np.tan(np.radians(camera.fov_y) / 2) / height


def _directional(samples=2, bounces=1, seed=0) -> BakeConfig:
    return BakeConfig(samples=samples, bounces=bounces, env="", albedo=ALBEDO, seed=seed,
                      lights=(f"dir:{KEY[0]},{KEY[1]},{KEY[2]}:{E0[0]},{E0[1]},{E0[2]}",))


def test_uniform_sky_gives_albedo_times_sky_and_the_analytic_silhouette(sphere):
    """A convex surface under a uniform sky L: every path escapes at once, so each sample
    is exactly albedo·L (any bounce count) and the standard error is 0. The mask is the
    ray–sphere silhouette up to one pixel (plus the mesh error) from the outline."""
    vol, camera, origins, dirs = sphere
    sky = np.array([1.0, 0.5, 0.25])
    config = BakeConfig(samples=20, bounces=2, env="constant:1,0.5,0.25", albedo=ALBEDO)
    image, stats = render_reference(vol, 0.5, origins, dirs, config, workers=2)
    m = image.mask
    assert m.sum() > 1000
    np.testing.assert_allclose(image.radiance[m], np.broadcast_to(np.array(ALBEDO) * sky,
                                                                  (m.sum(), 3)), rtol=1e-12)
    assert (image.stderr[m] == 0).all() and (stats.count[m] == 20).all()
    # background: the sky seen along the ray, no samples, no error
    np.testing.assert_allclose(image.radiance[~m], np.broadcast_to(sky, ((~m).sum(), 3)))
    assert (image.stderr[~m] == 0).all() and (stats.count[~m] == 0).all()
    margin = _pixel_size(camera, SIZE[1]) + MESH_ERROR_VOXELS * vol.spacing[0]
    inside, _, _ = _ray_sphere(camera, origins, dirs, SPHERE_RADIUS - margin)
    outside = ~_ray_sphere(camera, origins, dirs, SPHERE_RADIUS + margin)[0]
    assert m[inside].all() and not m[outside].any()
    radius_px = np.sqrt(m.sum() / np.pi)
    assert (~inside & ~outside).sum() < 2 * np.pi * radius_px * 3  # a thin ring


def test_directional_light_follows_the_cosine_law(sphere):
    """L = albedo·E0·max(0, n·l)/π with the analytic normal. One shadow ray per light and
    bounce rays that all escape into a black sky: no noise at all.

    Bound: the smoothed normal is within 1° of the normal at the mesh hit, so |Δ(n·l)| ≤
    sin 1°; the analytic hit lies ≤ 0.05 voxel / cos θ further along the ray, turning its
    normal by ≤ that over R; pixels with cos θ < 0.3 (near the outline) are left out.
    """
    vol, camera, origins, dirs = sphere
    image, _ = render_reference(vol, 0.5, origins, dirs, _directional(), workers=2)
    hit, normals, cos_view = _ray_sphere(camera, origins, dirs)
    sel = hit & image.mask & (cos_view > 0.3)
    expected = np.array(ALBEDO) * E0 / np.pi * np.clip(normals @ KEY, 0, None)[:, None]
    shift = MESH_ERROR_VOXELS * vol.spacing[0] / 0.3 / SPHERE_RADIUS  # radians
    bound = np.array(ALBEDO) * E0 / np.pi * (np.sin(np.radians(1.0)) + shift)
    error = np.abs(image.radiance - expected)[sel]
    assert sel.sum() > 1000
    assert (error <= bound).all(), (error.max(0), bound)
    assert (image.stderr[image.mask] == 0).all()


def _gl_frame(vol, iso, settings, view):
    """The GL renderer's frame (OSMesa) seen by `default_camera` from `view`, or skip where
    there is no OSMesa."""
    from isolume.app.render.glcontext import GLUnavailable
    from isolume.app.render.offscreen import render_volume

    try:
        frame, _ = render_volume(vol, iso, settings, camera=default_camera(vol, view),
                                 backend="osmesa")
    except GLUnavailable as exc:
        pytest.skip(f"no OSMesa: {exc}")
    return frame


def test_agrees_with_gl_lambert_on_the_same_camera(sphere):
    """GL `lambert` with one key light and no headlight is the same directional light
    without shadows; on a convex sphere they must agree pixel by pixel away from the
    outline, within both normals' 1° bounds: |ΔL| ≤ albedo·E0/π · 2 sin 1°. Mirrored
    rows or columns, or a shifted camera, would break this by far (the light is oblique)."""
    vol, _, origins, dirs = sphere
    settings = RenderSettings(size=SIZE, shading="lambert", tonemap="clamp",
                              key_dir=tuple(KEY), key_irradiance=tuple(E0),
                              head_irradiance=(0, 0, 0), albedo=ALBEDO)
    frame = _gl_frame(vol, 0.5, settings, VIEW)
    image, _ = render_reference(vol, 0.5, origins, dirs, _directional(), workers=2)
    w, h = SIZE
    ref, mask = image.radiance.reshape(h, w, 3), image.mask.reshape(h, w)
    both = ndimage.binary_erosion(mask & frame.mask, iterations=2)
    bound = np.array(ALBEDO) * E0 / np.pi * 2 * np.sin(np.radians(1.0))
    error = np.abs(ref - frame.linear)[both]
    assert both.sum() > 1000
    assert (error <= bound).all(), (error.max(0), bound)
    assert np.median(error[:, 0]) < 0.1 * bound[0]


def test_surface_mask_matches_gl_on_an_asymmetric_volume():
    """The engine from an oblique view: the reference's surface pixels and GL's differ only
    next to GL's outline (rasterisation and ray casting both sample pixel centres)."""
    vol = make("engine", 48)
    view = (35.0, 30.0, 1.5)
    frame = _gl_frame(vol, 0.3, RenderSettings(size=SIZE, shading="lambert"), view)
    origins, dirs = default_camera(vol, view).primary_rays(*SIZE)
    config = BakeConfig(samples=1, bounces=0)
    with ReferenceTracer(vol, 0.3, origins, dirs, config, workers=1) as tracer:
        mask = tracer.image(PixelStats.empty(tracer.pixels)).mask.reshape(SIZE[1], SIZE[0])
    gl = frame.mask
    outline = ndimage.binary_dilation(gl, iterations=1) & ~ndimage.binary_erosion(gl)
    differ = mask != gl
    assert gl.sum() > 1500
    assert not differ[~outline].any()
    assert differ.sum() < 0.1 * outline.sum()


def _torus_scene(samples, seed=1, size=(64, 48)):
    """(volume, origins, dirs, config): a torus under a sky with a sun, one bounce."""
    vol = make("torus", 40)
    origins, dirs = default_camera(vol, (20.0, 40.0, 1.4)).primary_rays(*size)
    return vol, origins, dirs, BakeConfig(samples=samples, bounces=1, env="sky:sun=2",
                                          seed=seed)


def _torus(samples, seed=1, workers=2, stats=None):
    vol, origins, dirs, config = _torus_scene(samples, seed)
    return render_reference(vol, 0.5, origins, dirs, config, workers=workers, stats=stats)


def test_standard_error_matches_the_spread_of_independent_runs():
    """z = (a − b)/sqrt(se_a² + se_b²) over surface pixels of two seeds: standard normal
    when the standard errors are right. With N pixels, the sample std of z has a standard
    deviation of about 1/sqrt(2N); variances estimated from n = 32 samples inflate it by
    about sqrt(df/(df − 2)) − 1 ≈ 1.6 % (df = 62). Allow 4 sigma plus that."""
    a, _ = _torus(32, seed=1)
    b, _ = _torus(32, seed=2)
    m = a.mask
    se = np.hypot(a.stderr[m, 1], b.stderr[m, 1])
    assert (se > 0).all()
    z = (a.radiance[m, 1] - b.radiance[m, 1]) / se
    n = len(z)
    assert n > 500
    assert abs(z.std() - 1) < 0.02 + 4 / np.sqrt(2 * n), z.std()
    inside = np.mean(np.abs(z) < 1)  # 68.3 % for a normal; binomial sd sqrt(p(1-p)/N)
    assert abs(inside - 0.683) < 4 * np.sqrt(0.683 * 0.317 / n), inside


def test_same_image_with_any_worker_count_and_after_resuming():
    one, s1 = _torus(20, workers=1)
    three, s3 = _torus(20, workers=3)
    for field in ("count", "shift", "s1", "s2"):
        assert np.array_equal(getattr(s1, field), getattr(s3, field)), field
    assert np.array_equal(one.radiance, three.radiance)
    _, partial = _torus(8)
    resumed, _ = _torus(20, stats=partial)
    np.testing.assert_allclose(resumed.radiance, one.radiance, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(resumed.stderr, one.stderr, rtol=1e-6, atol=1e-9)


def test_a_stopped_run_keeps_whole_passes_and_resumes_exactly():
    """Stop after the first pass of 16 samples (as Ctrl-C does), then finish: the same
    samples as one uninterrupted run."""
    vol, origins, dirs, config = _torus_scene(40)
    with ReferenceTracer(vol, 0.5, origins, dirs, config, workers=2) as tracer:
        stats, stop = PixelStats.empty(tracer.pixels), threading.Event()
        assert not tracer.run(stats, after_pass=stop.set, stop=stop)
        counts = stats.count[tracer.hits.pixels]
        assert counts.min() == counts.max() == 16
        assert tracer.run(stats)
        stopped = tracer.image(stats)
    whole, _ = _torus(40)
    np.testing.assert_allclose(stopped.radiance, whole.radiance, rtol=1e-12)
    np.testing.assert_allclose(stopped.stderr, whole.stderr, rtol=1e-9)


# -- command line ---------------------------------------------------------------------
def _run(capsys, *argv):
    status = main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


COMMON = ("reference", "synthetic:torus:32", "--size", "40x30", "--env", "sky", "--bounces",
          "1", "--workers", "2")


def test_cli_writes_exr_sidecar_and_resumes(tmp_path, capsys):
    out = tmp_path / "ref.exr"
    status, text, err = _run(capsys, *COMMON, "--spp", "8", "--out", str(out))
    assert status == 0, err
    assert f"wrote {out}" in text and "8 spp" in text
    channels = read_exr(out)
    assert channels["RGB"].shape == (30, 40, 3) and channels["stderr"].shape == (30, 40, 3)
    mask = channels["mask"]
    assert set(np.unique(mask)) == {0.0, 1.0} and mask.sum() > 50
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["spp"] == 8 and side["spp_min"] == 8 and side["rays"] > 0
    assert side["camera"]["size"] == [40, 30] and side["config"]["bounces"] == 1
    status, text, err = _run(capsys, *COMMON, "--spp", "16", "--out", str(out))
    assert status == 0, err
    resumed = read_exr(out)
    direct = tmp_path / "direct.exr"
    assert _run(capsys, *COMMON, "--spp", "16", "--out", str(direct))[0] == 0
    fresh = read_exr(direct)
    np.testing.assert_allclose(resumed["RGB"], fresh["RGB"], rtol=1e-6)
    np.testing.assert_allclose(resumed["stderr"], fresh["stderr"], rtol=1e-5)
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["spp_min"] == 16 and side["runs"] == 2
    # as many samples as asked, beyond a bake's cap on a texel's paths, added to those
    small, many = ("--size", "8x6", "--view", "30,20"), tmp_path / "many.exr"
    assert _run(capsys, *COMMON, *small, "--spp", "4", "--out", str(many))[0] == 0
    status, text, err = _run(capsys, *COMMON, *small, "--spp", "4100", "--out", str(many))
    assert status == 0 and "4100 spp" in text, err
    assert json.loads(many.with_suffix(".json").read_text())["runs"] == 2
    # the same --out with another camera is refused, and says what to do
    status, _, err = _run(capsys, *COMMON, "--spp", "16", "--view", "0,0",
                          "--out", str(out))
    assert status == 2 and "another volume, camera or lighting" in err


@pytest.mark.parametrize(
    ("make_args", "expected"),
    [
        (lambda t: ["--out", str(t / "missing" / "r.exr")], "does not exist"),
        (lambda t: ["--out", str(t / "r.png")], "must end in .exr"),
        (lambda t: ["--spp", "0", "--out", str(t / "r.exr")], "--spp 0"),
        (lambda t: ["--workers", "0", "--out", str(t / "r.exr")], "--workers 0"),
        (lambda t: ["--env", "none", "--out", str(t / "r.exr")], "nothing lights the scene"),
        (lambda t: ["--env", "sky:fog=1", "--out", str(t / "r.exr")], "unknown sky key"),
        (lambda t: ["--light", "dir:0,0,0:1,1,1", "--out", str(t / "r.exr")], "zero"),
        (lambda t: ["--iso", "7", "--out", str(t / "r.exr")], "outside the data range"),
        (lambda t: ["--view", "0,100", "--out", str(t / "r.exr")], "elevation"),
    ],
)
def test_bad_input_gives_one_line_and_status_2(tmp_path, capsys, make_args, expected):
    status, _, err = _run(capsys, "reference", "synthetic:sphere:16", "--size", "8x8",
                          *make_args(tmp_path))
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("isolume: error:"), err
    assert expected in lines[0]


def test_turning_a_sky_equals_moving_its_sun():
    """The sky's gradient depends on z only, so turning it by 90° about +z
    (``--env-rotation 90,0``) is the sky whose sun_az is 90° more. The two are traced
    with different samplers (the turned sky through its own methods, the other by the
    compiled sky kernels), so they agree within their combined noise (3 σ RMS); the sun
    left where it was misses by far more."""
    from isolume import volumes
    from isolume.baking import sh

    vol = volumes.load("synthetic:engine:24")
    iso = volumes.suggest_isovalues(vol)[0]
    origins, dirs = default_camera(vol, (30, 30, None)).primary_rays(24, 24)

    def trace(env, rotation=None):
        image, _ = render_reference(vol, iso, origins, dirs, BakeConfig(samples=128, env=env),
                                    env_rotation=rotation, workers=2)
        return image

    turned = trace("sky:sun=3", sh.rotation_from_az_el(90, 0))
    moved = trace("sky:sun=3,sun_az=135")
    m = turned.mask & moved.mask

    def rel(a, b):
        return np.sqrt(np.mean((a.radiance[m] - b.radiance[m]) ** 2)) / np.mean(b.radiance[m])

    noise = np.sqrt(np.mean(turned.stderr[m] ** 2 + moved.stderr[m] ** 2)) / np.mean(
        moved.radiance[m])
    assert rel(turned, moved) < 3 * noise
    assert rel(trace("sky:sun=3"), moved) > 3 * noise
