"""The comparison shading modes: shadow maps, fog, occlusion, lattice lookups.

Every check predicts pixels in numpy from the world positions of the `position` pass and
compares them with what the shaders drew.
"""

import numpy as np
import pytest

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.renderer import default_camera
from isolume.app.render.settings import SHADING_MODES, RenderError, RenderSettings
from isolume.app.render.shadows import light_view_proj
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import Lattice, LatticeGeometry, trilinear
from isolume.baking.plan import texel_values
from isolume.volumes.synthetic import make

RGB9E5_RELATIVE = 2.0**-9
"""GL_RGB9_E5 rounding: ≤ 2⁻⁹ of a texel's largest channel (9-bit shared-exponent
mantissas)."""
UNORM8_FILTER = 1.5 / 255
"""llvmpipe filters the R8 valid mask in 8-bit fixed point: three rounded lerps leave the
interpolated weight w of computed texels up to 1.5/255 off (exact where all are computed),
so E = (E·w) / w is off by up to E_max · 1.5/255 / w next to uncomputed texels."""


# -- scenes -------------------------------------------------------------------------------
def _plane(z: float, half: float, n: int = 16):
    """(vertices, normals, faces) of the square |x|, |y| ≤ half at height z, normal +z."""
    s = np.linspace(-half, half, n + 1)
    x, y = np.meshgrid(s, s)
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    quads = np.stack([i, i + 1, i + n + 2, i + n + 1], axis=-1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1)), faces


def _sphere(centre, radius: float, n_lat: int = 64, n_lon: int = 128):
    """(vertices, normals, faces) of a latitude-longitude sphere."""
    theta = np.linspace(0, np.pi, n_lat + 1)
    phi = np.linspace(0, 2 * np.pi, n_lon + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    normals = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    normals = normals.reshape(-1, 3)
    i = np.arange(n_lat)[:, None] * (n_lon + 1) + np.arange(n_lon)[None, :]
    quads = np.stack([i, i + n_lon + 1, i + n_lon + 2, i + 1], axis=-1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return np.asarray(centre) + radius * normals, normals, faces


def _merge(*meshes):
    vertices, normals, faces, offset = [], [], [], 0
    for v, n, f in meshes:
        vertices.append(v)
        normals.append(n)
        faces.append(f + offset)
        offset += len(v)
    return (np.concatenate(vertices).astype(np.float32),
            np.concatenate(normals).astype(np.float32), np.concatenate(faces).astype(np.uint32))


def _render(renderer, camera, settings, **changes):
    """Linear radiance (H, W, 3) and surface mask (H, W) for `settings` with `changes`."""
    frame = renderer.render(camera, RenderSettings(**{**settings.__dict__, **changes}))
    return frame.linear.astype(np.float64), frame.mask


def _positions(renderer, camera, size):
    """(H, W, 3) world position of every pixel and the (H, W) surface mask."""
    return _render(renderer, camera, RenderSettings(size=size, shading="position"))


# -- shadows ------------------------------------------------------------------------------
BALL_CENTRE, BALL_RADIUS = np.array([0.0, 0.0, 0.45]), 0.2
KEY = np.array([0.35, -0.25, 1.0]) / np.linalg.norm([0.35, -0.25, 1.0])


def _shadow_scene(renderer):
    mesh = _merge(_plane(0.0, 1.0), _sphere(BALL_CENTRE, BALL_RADIUS))
    renderer.set_mesh(*mesh)
    lo, hi = np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 0.7])
    renderer.set_bounds(lo, hi)
    camera = Camera(azimuth=25, elevation=50, distance=1.2, target=(0, 0, 0.2), scale=2.0)
    return camera, float(np.linalg.norm(hi - lo)) / 2


def _ball_clearance(points: np.ndarray) -> np.ndarray:
    """(N,) distance from the ray p + t·KEY (t > 0) to the ball's surface, world units:
    negative where the ray passes through the ball (p in its umbra), +inf where the ball
    lies behind p."""
    to_centre = BALL_CENTRE - points
    along = to_centre @ KEY
    miss = np.linalg.norm(to_centre - along[:, None] * KEY, axis=1) - BALL_RADIUS
    return np.where(along > 0, miss, np.inf)


@pytest.mark.parametrize("resolution", [512, 2048])
def test_shadow_map_matches_analytic_umbra(renderer, resolution):
    """Umbra pixels get only the headlight, lit pixels exactly `lambert`; only a band of
    PCF footprint + facet error around the shadow's edge may be in between."""
    camera, radius = _shadow_scene(renderer)
    size = (200, 160)
    settings = RenderSettings(size=size, shading="lambert_shadow", tonemap="clamp",
                              key_dir=tuple(KEY), head_irradiance=(0.3, 0.3, 0.3),
                              shadow_resolution=resolution)
    shadowed, mask = _render(renderer, camera, settings)
    lit, _ = _render(renderer, camera, settings, shading="lambert")
    head_only, _ = _render(renderer, camera, settings, shading="lambert",
                           key_irradiance=(0, 0, 0))
    points, _ = _positions(renderer, camera, size)
    clearance = _ball_clearance(points[mask])
    # PCF reads depths up to 1 + √2 shadow texels from the looked-up point (a diagonal tap
    # plus its bilinear neighbours), measured across the light like `clearance`; the map
    # is rasterised at texel centres (½ texel more); the 128-gon ball's silhouette lies
    # within r (1 − cos(π/64)) of the sphere's
    texel = 2 * 1.01 * radius / resolution
    band = (1 + np.sqrt(2) + 0.5) * texel + BALL_RADIUS * (1 - np.cos(np.pi / 64))
    umbra, clear = clearance < -band, clearance > band
    assert umbra.sum() > 500 and clear.sum() > 10_000
    np.testing.assert_allclose(shadowed[mask][umbra], head_only[mask][umbra], atol=1e-5)
    np.testing.assert_allclose(shadowed[mask][clear], lit[mask][clear], atol=1e-5)  # no acne
    # the band left out is a few pixels wide: a pixel spans this much at the ball
    pixel = 2 * np.tan(np.radians(camera.fov_y) / 2) * np.linalg.norm(
        camera.eye - BALL_CENTRE) / size[1]
    assert 2 * band < 3 * pixel * 2048 / resolution


def test_phong_shadow_darkens_only_the_key_light(renderer):
    camera, _ = _shadow_scene(renderer)
    settings = RenderSettings(size=(120, 96), shading="phong_shadow", tonemap="clamp",
                              key_dir=tuple(KEY), head_irradiance=(0.3, 0.3, 0.3))
    shadowed, mask = _render(renderer, camera, settings)
    head_only, _ = _render(renderer, camera, settings, shading="phong",
                           key_irradiance=(0, 0, 0))
    points, _ = _positions(renderer, camera, (120, 96))
    umbra = _ball_clearance(points[mask]) < -0.02
    assert umbra.sum() > 50
    np.testing.assert_allclose(shadowed[mask][umbra], head_only[mask][umbra], atol=1e-5)


def test_light_view_encloses_the_sphere():
    """The light's clip space holds the sphere; depth runs from the point nearest the
    light (−1) to the farthest (+1)."""
    centre, radius = np.array([1.0, -2.0, 0.5]), 3.0
    m = light_view_proj(KEY, centre, radius)
    ends = np.array([centre + radius * KEY, centre - radius * KEY, centre])
    clip = (m @ np.c_[ends, np.ones(3)].T).T
    np.testing.assert_allclose(clip[:, 2], [-1, 1, 0], atol=1e-12)
    np.testing.assert_allclose(clip[:, :2], 0, atol=1e-12)
    side = np.cross(KEY, [1.0, 0, 0])
    edge = m @ np.r_[centre + radius * side / np.linalg.norm(side), 1]
    assert np.isclose(np.hypot(edge[0], edge[1]), 1.0)


# -- fog ----------------------------------------------------------------------------------
def test_fog_falls_off_exponentially_with_eye_distance(renderer):
    renderer.set_mesh(*_merge(_plane(0.0, 1.0)))
    lo, hi = np.array([-1.0, -1.0, -0.2]), np.array([1.0, 1.0, 0.2])
    renderer.set_bounds(lo, hi)
    camera = Camera(azimuth=0, elevation=15, distance=1.0, target=(0, 0, 0), scale=2.0)
    background = (0.05, 0.06, 0.07)
    settings = RenderSettings(size=(96, 128), shading="lambert_fog", tonemap="clamp",
                              key_dir=(0, 0, 1), head_irradiance=(0, 0, 0), fog_density=2.0,
                              background=background, exposure=2.0)
    fogged, mask = _render(renderer, camera, settings)
    clear, _ = _render(renderer, camera, settings, shading="lambert")
    points, _ = _positions(renderer, camera, settings.size)
    distance = np.linalg.norm(points[mask] - camera.eye, axis=1)
    # fog begins at the near side of the bounds' sphere, density per diagonal
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    start = np.linalg.norm(centre - camera.eye) - radius
    transmittance = np.exp(-2.0 * np.maximum(distance - start, 0) / (2 * radius))
    fog_color = np.array(background) / 2.0  # shown unexposed, like the background
    expected = fog_color + transmittance[:, None] * (clear[mask] - fog_color)
    np.testing.assert_allclose(fogged[mask], expected, rtol=1e-4, atol=1e-6)
    assert transmittance.min() < 0.4  # the plane reaches well into the fog
    brightness = fogged[mask].sum(axis=1)[np.argsort(distance)]
    assert (np.diff(brightness) <= 1e-6).all()  # monotonic: farther is darker


# -- lattice lookups ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def lookup_scene():
    """A sphere volume, its mesh, and a coarse irradiance lattice of random texels with
    about one in six not computed."""
    vol = make("sphere", 40)
    mesh = volumes.isosurface(vol, 0.5)
    geometry = LatticeGeometry.for_volume(vol, 0.25)
    rng = np.random.default_rng(6)
    values = rng.uniform(0.1, 1.0, (*geometry.shape, 3)).astype(np.float32)
    samples = (rng.random(geometry.shape) > 1 / 6).astype(np.uint32)
    lattice = Lattice(geometry, values, samples, np.zeros(geometry.shape, np.float32),
                      np.ones(geometry.shape, bool), {"kind": "irradiance"})
    return vol, mesh, lattice, texel_values(vol, geometry)


def _cell_corners(lattice, coords):
    """(N, 8, 3) zyx indices of the 2×2×2 texels around (N, 3) texel coordinates, corner
    k = x + 2y + 4z (the shader's order), with the base clamped as GL filtering does."""
    shape = np.array(lattice.geometry.shape)
    base = np.clip(np.floor(coords).astype(int), 0, shape - 2)
    k = np.arange(8)
    offsets = np.stack([(k >> 2) & 1, (k >> 1) & 1, k & 1], axis=1)  # zyx
    return base[:, None, :] + offsets[None]


def _pick(lattice, corners, score):
    """(N, 3) values and (N,) found flag of the computed corner with the lowest score
    (first in corner order on ties), and (N,) the margin to the runner-up."""
    idx = tuple(corners[..., a] for a in range(3))
    valid = lattice.samples[idx] > 0
    score = np.where(valid, score, np.inf)
    order = np.argsort(score, axis=1, kind="stable")
    best = order[:, 0]
    rows = np.arange(len(best))
    ranked = np.take_along_axis(score, order[:, :2], axis=1)
    margin = np.where(np.isfinite(ranked[:, 1]), ranked[:, 1] - ranked[:, 0], np.inf)
    return lattice.values[idx][rows, best], valid.any(axis=1), margin


def nearest_texel(lattice, coords):
    """The computed texel of the 8 around each point whose centre is nearest (world)."""
    corners = _cell_corners(lattice, coords)
    step = lattice.geometry.texel_size[::-1]  # zyx
    d2 = (((coords[:, None, :] - corners) * step) ** 2).sum(axis=2)
    return _pick(lattice, corners, d2)


def closest_isovalue_texel(lattice, coords, rho, iso):
    """The computed texel of the 8 around each point whose isovalue is nearest `iso`
    (float32, as the shader computes it)."""
    corners = _cell_corners(lattice, coords)
    gap = np.abs(rho[tuple(corners[..., a] for a in range(3))] - np.float32(iso))
    return _pick(lattice, corners, gap)


def bspline(lattice, coords):
    """(N, 3) uniform cubic B-spline of the computed texels (weights renormalised over
    them) and (N,) their total weight; indices past the edge repeat the edge texel."""
    shape = np.array(lattice.geometry.shape)
    base = np.floor(coords).astype(int)
    a = coords - base
    weights = np.stack([(1 - a) ** 3, 3 * a**3 - 6 * a**2 + 4,
                        -3 * a**3 + 3 * a**2 + 3 * a + 1, a**3], axis=1) / 6  # (N, 4, 3)
    valid = (lattice.samples > 0).astype(np.float64)
    num, den = np.zeros((len(coords), 3)), np.zeros(len(coords))
    for i in range(4):
        for j in range(4):
            for k in range(4):
                idx = np.clip(base + np.array([i, j, k]) - 1, 0, shape - 1)
                w = weights[:, i, 0] * weights[:, j, 1] * weights[:, k, 2]
                v = valid[idx[:, 0], idx[:, 1], idx[:, 2]]
                num += (w * v)[:, None] * lattice.values[idx[:, 0], idx[:, 1], idx[:, 2]]
                den += w * v
    return num / np.maximum(den, 1e-12)[:, None], den


def _lookup_frames(renderer, lookup_scene, shading):
    """Lattice radiance with albedo π (so radiance = E) and the pixels' texel coords."""
    vol, mesh, lattice, rho = lookup_scene
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
    renderer.set_lattice(lattice, texel_isovalues=rho)
    camera = default_camera(vol, (30.0, 25.0, 1.3))
    size = (160, 160)
    settings = RenderSettings(size=size, shading=shading, tonemap="clamp",
                              albedo=(np.pi, np.pi, np.pi))
    radiance, mask = _render(renderer, camera, settings)
    points, _ = _positions(renderer, camera, size)
    coords = lattice.geometry.to_texel_coords(points[mask])
    return radiance[mask], coords


def _filtered_atol(weight: np.ndarray, largest: float = 1.0) -> np.ndarray:
    """(N,) tolerance of a filtered lookup with (N,) weight of computed texels, for texel
    values up to `largest`: storage rounding, plus the valid mask's filtering error
    where some texels are not computed."""
    mask_error = np.where(weight < 1 - 1e-9, UNORM8_FILTER / np.maximum(weight, 1e-9), 0)
    return largest * (RGB9E5_RELATIVE + mask_error) + 1e-6


STORAGE_ATOL = RGB9E5_RELATIVE * 1.0 + 1e-6  # texel values ≤ 1, one texel per pixel


def _near_cell_boundary(coords, lattice, tol=1e-3):
    """(N,) points within `tol` texels of a plane where the 2×2×2 cell changes (float32
    on the GPU against float64 here may pick the other cell)."""
    inside = np.clip(coords, 0, np.array(lattice.geometry.shape) - 1)
    return (np.abs(inside - np.round(inside)) < tol).any(axis=1)


def test_trilinear_lookup_matches_lattice_sample(renderer, lookup_scene):
    _, _, lattice, _ = lookup_scene
    radiance, coords = _lookup_frames(renderer, lookup_scene, "irradiance")
    points = lattice.geometry.lo + (coords[:, ::-1] + 0.5) * lattice.geometry.texel_size
    want = lattice.sample(points, normalized=True)
    weight = trilinear((lattice.samples > 0)[..., None].astype(np.float64), coords)[:, 0]
    baked = weight >= 0.25 + UNORM8_FILTER  # below 0.25 the shader blends to local shading
    assert baked.mean() > 0.9 and (weight < 1).mean() > 0.3
    error = np.abs(radiance - want).max(axis=1)
    assert (error <= _filtered_atol(weight))[baked].all(), error[baked].max()


def test_nearest_lookup_picks_the_nearest_computed_texel(renderer, lookup_scene):
    _, _, lattice, _ = lookup_scene
    radiance, coords = _lookup_frames(renderer, lookup_scene, "irradiance_nearest")
    want, found, margin = nearest_texel(lattice, coords)
    sure = found & (margin > 1e-4 * lattice.geometry.texel_size.min() ** 2)
    sure &= ~_near_cell_boundary(coords, lattice)
    assert sure.mean() > 0.9
    np.testing.assert_allclose(radiance[sure], want[sure], atol=STORAGE_ATOL)
    # the lookup is piecewise constant: far fewer distinct values than pixels
    assert len(np.unique(np.round(radiance[sure], 4), axis=0)) < 0.1 * sure.sum()


def test_closest_isovalue_lookup_picks_the_texel_nearest_the_isovalue(renderer,
                                                                      lookup_scene):
    _, mesh, lattice, rho = lookup_scene
    radiance, coords = _lookup_frames(renderer, lookup_scene, "irradiance_closest")
    want, found, _ = closest_isovalue_texel(lattice, coords, rho, mesh.iso)
    sure = found & ~_near_cell_boundary(coords, lattice)
    assert sure.mean() > 0.9
    np.testing.assert_allclose(radiance[sure], want[sure], atol=STORAGE_ATOL)
    nearest, _, _ = nearest_texel(lattice, coords)
    assert (np.abs(want - nearest).max(axis=1) > 0.01).mean() > 0.2  # a different rule


def test_bspline_lookup_matches_the_cubic_b_spline(renderer, lookup_scene):
    _, _, lattice, _ = lookup_scene
    radiance, coords = _lookup_frames(renderer, lookup_scene, "irradiance_bspline")
    want, weight = bspline(lattice, coords)
    baked = weight >= 0.25 + UNORM8_FILTER
    assert baked.mean() > 0.9 and (weight < 1).mean() > 0.3
    error = np.abs(radiance - want).max(axis=1)
    assert (error <= _filtered_atol(weight))[baked].all(), error[baked].max()
    trilinear_want = lattice.sample(
        lattice.geometry.lo + (coords[:, ::-1] + 0.5) * lattice.geometry.texel_size,
        normalized=True)
    assert np.abs(want - trilinear_want)[baked].mean() > 0.02  # a different filter


# -- vicinity shading and ambient occlusion ---------------------------------------------
def _occlusion_lattice(lattice, env="constant:2,2,2", bounces=0):
    return Lattice(lattice.geometry, lattice.values, lattice.samples, lattice.second,
                   lattice.active, {"kind": "irradiance"},
                   config=BakeConfig(env=env, bounces=bounces))


def test_vicinity_and_ao_read_a_constant_sky_lattice(renderer, lookup_scene):
    """vicinity = albedo·E/π; ao = albedo·E/(π·L_sky)·E_hemi/π (no key light)."""
    vol, mesh, lattice, _ = lookup_scene
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces)
    renderer.set_lattice(_occlusion_lattice(lattice))
    camera = default_camera(vol)
    ambient = (0.6, 0.5, 0.4)  # the same sky and ground: E_hemi does not depend on n
    settings = RenderSettings(size=(96, 96), shading="vicinity", tonemap="clamp",
                              albedo=(0.5, 0.6, 0.7), sky_irradiance=ambient,
                              ground_irradiance=ambient)
    vicinity, mask = _render(renderer, camera, settings)
    ao, _ = _render(renderer, camera, settings, shading="ao")
    points, _ = _positions(renderer, camera, settings.size)
    e = lattice.sample(points[mask], normalized=True)
    weight = trilinear((lattice.samples > 0)[..., None].astype(np.float64),
                       lattice.geometry.to_texel_coords(points[mask]))[:, 0]
    baked = weight >= 0.25 + UNORM8_FILTER
    albedo = np.array(settings.albedo)
    want = {"vicinity": albedo * e / np.pi,
            "ao": albedo * e / (2 * np.pi) * np.array(ambient) / np.pi}
    for name, got in (("vicinity", vicinity), ("ao", ao)):
        error = np.abs(got[mask] - want[name]).max(axis=1)
        atol = _filtered_atol(weight, np.abs(want[name]).max())
        assert (error <= atol)[baked].all(), (name, error[baked].max())


@pytest.mark.parametrize("env, bounces", [("constant:1,1,1", 2), ("sky", 0)])
def test_occlusion_modes_refuse_other_bakes(renderer, lookup_scene, env, bounces):
    _, mesh, lattice, _ = lookup_scene
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces)
    renderer.set_lattice(_occlusion_lattice(lattice, env, bounces))
    for shading in ("vicinity", "ao"):
        with pytest.raises(RenderError, match="constant sky with no bounces"):
            renderer.check_mode(shading)


def test_closest_lookup_needs_texel_isovalues_and_the_isovalue(renderer, lookup_scene):
    _, mesh, lattice, rho = lookup_scene
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
    renderer.set_lattice(lattice)
    with pytest.raises(RenderError, match="texel isovalues"):
        renderer.check_mode("irradiance_closest")
    renderer.set_lattice(lattice, texel_isovalues=rho)
    renderer.check_mode("irradiance_closest")
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces)
    with pytest.raises(RenderError, match="isovalue"):
        renderer.check_mode("irradiance_closest")


# -- every mode ---------------------------------------------------------------------------
def _lattice_for(shading, lookup_scene):
    """A lattice (and SH environment) that `shading` can draw."""
    _, _, lattice, _ = lookup_scene
    if shading == "sh":
        meta = {"kind": "sh", "sh_order": 2}
        values = np.tile([np.pi, 0.0, 1.0, 0.0], (*lattice.geometry.shape, 1))
        sh = Lattice(lattice.geometry, values.astype(np.float32), lattice.samples,
                     lattice.second, lattice.active, meta)
        return sh, np.array([[0.5, 0.5, 0.5], [0, 0, 0], [0.2, 0.2, 0.2], [0, 0, 0]])
    if SHADING_MODES[shading].lattice == "occlusion":
        return _occlusion_lattice(lattice), None
    return lattice, None


@pytest.mark.parametrize("shading", list(SHADING_MODES))
def test_every_mode_renders(renderer, lookup_scene, shading):
    vol, mesh, _, rho = lookup_scene
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
    renderer.set_bounds(*vol.box)
    lattice, env = _lattice_for(shading, lookup_scene)
    renderer.set_lattice(lattice, texel_isovalues=rho)
    renderer.set_environment(env)
    frame = renderer.render(default_camera(vol), RenderSettings(size=(64, 64), shading=shading,
                                                                shadow_resolution=256))
    assert frame.mask.mean() > 0.1
    assert np.isfinite(frame.linear).all() and frame.linear[frame.mask].max() > 0.02
