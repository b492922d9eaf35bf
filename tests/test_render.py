"""Off-screen rendering: predicted pixels, EGL = OSMesa, tone mapping."""

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.renderer import default_camera
from isolume.app.render.settings import RenderSettings
from isolume.volumes.synthetic import SPHERE_RADIUS, make


def _sphere_scene(renderer, settings, size=96):
    vol = make("sphere", size)
    mesh = volumes.isosurface(vol, 0.5)
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces)
    camera = default_camera(vol, (20.0, 25.0, 1.6))
    return camera, renderer.render(camera, settings)


def _ray_sphere(camera: Camera, width: int, height: int):
    """Analytic hits of primary rays with the sphere: (hit mask (H, W), normals (H, W, 3))."""
    origins, dirs = camera.primary_rays(width, height)
    oc = origins - np.asarray(camera.target)
    b = (oc * dirs).sum(1)
    c = (oc * oc).sum(1) - SPHERE_RADIUS**2
    disc = b * b - c
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    normals = (oc + t[:, None] * dirs) / SPHERE_RADIUS
    return hit.reshape(height, width), normals.reshape(height, width, 3)


def test_sphere_silhouette_matches_projection(renderer):
    settings = RenderSettings(size=(160, 120), shading="lambert")
    camera, frame = _sphere_scene(renderer, settings)
    predicted, _ = _ray_sphere(camera, 160, 120)
    differ = frame.mask != predicted
    # Only pixels whose centre lies within ~one pixel of the analytic outline may differ
    # (the mesh is a polygonal approximation, vertex error < 0.03 voxel); count them
    # against the outline length 2*pi*r in pixels.
    radius_px = np.sqrt(predicted.sum() / np.pi)
    assert differ.sum() <= 2 * np.pi * radius_px * 0.5
    assert frame.mask.sum() > 0.9 * predicted.sum()


def test_lambert_radiance_matches_cosine_law(renderer):
    """Key light only, no tone curve: L = albedo * E * max(0, n.l) / pi on every pixel."""
    key = np.array([0.3, -0.5, 0.8])
    key /= np.linalg.norm(key)
    settings = RenderSettings(
        size=(128, 128), shading="lambert", tonemap="clamp", key_dir=tuple(key),
        key_irradiance=(2.0, 1.0, 0.5), head_irradiance=(0, 0, 0), albedo=(0.5, 0.6, 0.7),
    )
    camera, frame = _sphere_scene(renderer, settings)
    hit, normals = _ray_sphere(camera, 128, 128)
    both = hit & frame.mask
    expected = (
        np.array(settings.albedo) * np.array(settings.key_irradiance) / np.pi
        * np.clip(normals @ key, 0, None)[..., None]
    )
    error = np.abs(frame.linear - expected)[both]
    # Normals are interpolated across triangles of a 96^3 sphere: angular error < 1 degree
    # gives |dL| <= L_max * sin(1 deg) = 0.32 * 0.017 = 0.006; pixel centres that see a
    # different facet than the analytic sphere add a little at grazing angles.
    assert np.median(error) < 0.003
    assert np.percentile(error, 99) < 0.02
    assert (frame.linear[~frame.mask] == 0).all()


def test_srgb_encoding_of_known_radiance(renderer):
    settings = RenderSettings(
        size=(64, 64), shading="lambert", tonemap="clamp", key_dir=(0, 0, 1),
        key_irradiance=(0, 0, 0), head_irradiance=(np.pi, np.pi, np.pi), albedo=(0.5, 0.5, 0.5),
        background=(0.2, 0.2, 0.2),
    )
    _, frame = _sphere_scene(renderer, settings, size=48)
    centre = frame.linear[32, 32]
    # headlight at normal incidence at the centre: L = 0.5 * pi / pi = 0.5 (cos ~ 1)
    np.testing.assert_allclose(centre, 0.5, atol=0.005)
    srgb = lambda c: 255 * (1.055 * c ** (1 / 2.4) - 0.055)  # noqa: E731
    assert abs(int(frame.srgb[32, 32, 0]) - srgb(float(centre[0]))) <= 1
    assert abs(int(frame.srgb[0, 0, 0]) - srgb(0.2)) <= 1  # background, linear 0.2


@pytest.mark.parametrize("shading", ["lambert", "phong", "lambert_hemi", "phong_hemi"])
def test_every_local_mode_renders(renderer, shading):
    _, frame = _sphere_scene(renderer, RenderSettings(size=(64, 64), shading=shading), size=32)
    assert frame.mask.mean() > 0.1
    assert np.isfinite(frame.linear).all() and frame.linear[frame.mask].max() > 0.05


def test_hemisphere_ambient_brightens_the_unlit_side(renderer):
    base = dict(size=(64, 64), key_dir=(0, 0, 1), head_irradiance=(0, 0, 0))
    _, plain = _sphere_scene(renderer, RenderSettings(shading="lambert", **base), size=32)
    _, hemi = _sphere_scene(renderer, RenderSettings(shading="lambert_hemi", **base), size=32)
    assert (hemi.linear[hemi.mask].mean()) > plain.linear[plain.mask].mean() + 0.05


def _cli_render(tmp_path, backend, shading):
    out = tmp_path / f"{backend}.png"
    cmd = [sys.executable, "-m", "isolume.app.cli", "render", "synthetic:torus:40",
           "--size", "96x72", "--gl", backend, "--shading", shading, "--out", str(out)]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    return result, out


@pytest.mark.parametrize("shading", ["phong_hemi", "phong_shadow"])
def test_egl_and_osmesa_agree(tmp_path, shading):
    """Same scene through EGL and OSMesa (both Mesa llvmpipe): at most 1/255 apart."""
    egl, egl_png = _cli_render(tmp_path, "egl", shading)
    if egl.returncode != 0:
        pytest.skip(f"EGL unavailable here: {egl.stderr.strip()}")
    osm, osm_png = _cli_render(tmp_path, "osmesa", shading)
    assert osm.returncode == 0, osm.stderr
    a = np.asarray(Image.open(egl_png), np.int16)
    b = np.asarray(Image.open(osm_png), np.int16)
    assert a.shape == (72, 96, 3)
    assert np.abs(a - b).max() <= 1


@pytest.mark.parametrize("suffix", [".png", ".exr"])
def test_a_picture_that_cannot_be_written_is_one_line_and_no_file(tmp_path, suffix):
    """A picture's write that fails half-way (files capped at 1 KiB, as a full disk
    would cut them): one `WriteError` line naming the file and the system's reason; no
    file or temporary file is left, and a picture already there stays as it was."""
    import resource

    from isolume.app.render.images import write_image
    from isolume.volumes.errors import WriteError

    rng = np.random.default_rng(0)
    linear = rng.random((64, 64, 3)).astype(np.float32)  # noise: kilobytes once compressed
    srgb = (linear * 255).astype(np.uint8)
    path = tmp_path / f"p{suffix}"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)

    def capped_write():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, hard))  # Python ignores SIGXFSZ
        try:
            write_image(path, linear, srgb)
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))

    with pytest.raises(WriteError, match=rf"p\{suffix}: cannot write the picture: File too "
                                         r"large; nothing was written$"):
        capped_write()
    assert not list(tmp_path.iterdir())
    write_image(path, linear[:2, :2], srgb[:2, :2])
    before = path.read_bytes()
    with pytest.raises(WriteError, match=r"the file there is left as it was$"):
        capped_write()
    assert path.read_bytes() == before and list(tmp_path.iterdir()) == [path]
