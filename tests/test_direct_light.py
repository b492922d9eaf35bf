"""Split direct light: lattices without the lights' and the sun's direct light,
which the renderer adds per pixel with shadow maps.

The baker's part is checked against the full estimate on the same paths (only the first
vertex may differ, by the direct irradiance computed independently here); the
renderer's shadows against analytic ones (an occluding disc and a sphere over a plane,
visible fraction of the sun disc by quadrature over its cone) and against ray-cast
shadows on a real isosurface.
"""

import dataclasses

import numpy as np
import pytest
from test_render_modes import _merge, _plane, _sphere
from test_viewer import _surface, _view, display  # noqa: F401  (display: an Xvfb fixture)

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.lights import lattice_direct_lights
from isolume.app.render.settings import RenderError, RenderSettings, direct_tiles
from isolume.baking import kernels, rng, sky_kernels
from isolume.baking.config import BakeConfig
from isolume.baking.environment import parse_env, sample_uniform_cone
from isolume.baking.errors import BakeError
from isolume.baking.integrator import (
    PathSettings,
    TracingLights,
    trace_paths,
    trace_whole_paths,
    whole_paths,
)
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.lighting import Lighting
from isolume.baking.lights import DirectionalLight, PointLight, SunLight, parse_light
from isolume.baking.trace import Scene


# -- configuration ------------------------------------------------------------------------
def test_direct_light_defaults_to_pixels_where_a_light_or_a_sun_is_present():
    assert BakeConfig(env="sky:sun=3").direct_light == "pixels"
    assert BakeConfig(env="constant:1,1,1", lights=("dir:0,0,1:1,1,1",)).direct_light == "pixels"
    assert BakeConfig(env="sky").direct_light == "lattice"  # no sun
    assert BakeConfig(env="constant:1,1,1").direct_light == "lattice"
    assert BakeConfig(mode="sh", env="sky:sun=3").direct_light == "lattice"
    assert BakeConfig(env="sky:sun=3", direct_light="lattice").direct_light == "lattice"


def test_direct_light_is_recorded_and_old_files_read_as_lattice():
    config = BakeConfig(env="sky:sun=3")
    assert BakeConfig.from_dict(config.to_dict()) == config
    old = {k: v for k, v in config.to_dict().items() if k != "direct_light"}
    assert BakeConfig.from_dict(old).direct_light == "lattice"
    assert not config.same_result_as(dataclasses.replace(config, direct_light="lattice"))


@pytest.mark.parametrize("changes, message", [
    ({"direct_light": "pixel"}, "expected one of pixels, lattice"),
    ({"mode": "sh", "direct_light": "pixels", "lights": ("dir:0,0,1:1,1,1",)},
     "not low-frequency"),
])
def test_bad_direct_light_settings_say_what_was_expected(changes, message):
    with pytest.raises(BakeError, match=message):
        BakeConfig(env="sky:sun=3", **changes)


def test_pixel_lights_are_the_lights_then_the_sun():
    lights = Lighting.parse("sky:sun=2,sun_az=90,sun_el=30,sun_radius=1.5",
                            ("dir:0,0,1:1,2,3", "point:1,2,3:4,4,4")).pixel_lights()
    assert lights[:2] == (parse_light("dir:0,0,1:1,2,3"), parse_light("point:1,2,3:4,4,4"))
    sun = lights[2]
    assert isinstance(sun, SunLight) and sun.radius == 1.5 and sun.irradiance == (2, 2, 2)
    np.testing.assert_allclose(sun.direction, [0, np.cos(np.pi / 6), 0.5], atol=1e-12)
    assert Lighting.parse("sky", ()).pixel_lights() == ()
    assert Lighting.parse("constant:1", ()).pixel_lights() == ()


# -- the baker's split --------------------------------------------------------------------
def test_bakes_leave_out_the_direct_light_their_config_sends_to_the_pixels():
    from isolume.baking.bake import tracing_lights

    assert tracing_lights(BakeConfig(env="sky:sun=3")).pixel_direct
    assert not tracing_lights(BakeConfig(env="sky:sun=3", direct_light="lattice")).pixel_direct


@pytest.fixture(scope="module")
def engine_starts():
    """Start points on the synthetic engine (concave: bounces reach the sun) and its scene."""
    vol = volumes.load("synthetic:engine:40")
    mesh = volumes.isosurface(vol, 0.3)
    scene = Scene(mesh.vertices, mesh.faces)
    pick = np.random.default_rng(3).choice(len(mesh.vertices), 600, replace=False)
    normals = mesh.normals[pick].astype(np.float64)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    origins = mesh.vertices[pick] + 0.25 * float(min(vol.spacing)) * normals
    return scene, origins.astype(np.float32), normals.astype(np.float32), vol


def _lighting(env: str, lights=(), pixel_direct=False) -> TracingLights:
    sky = parse_env(env)
    return TracingLights(sky, True, tuple(parse_light(s) for s in lights),
                    sky_kernels.sky_params(sky), pixel_direct=pixel_direct)


def _paths(engine_starts, samples: int):
    scene, origins, normals, vol = engine_starts
    texel = np.repeat(np.arange(len(origins)), samples)
    keys = rng.path_keys(7, texel, np.tile(np.arange(samples), len(origins)))
    settings = PathSettings(bounces=2, albedo=(0.8, 0.8, 0.8),
                            hit_offset=2e-3 * float(min(vol.spacing)))
    return scene, origins[texel], normals[texel], keys, texel, settings


def _direct_irradiance(scene, origins, normals, lights, sun: SunLight, rays: int = 256):
    """(P, 3) direct irradiance of `lights` and `sun` at the points, by shadow rays: one
    per directional light, `rays` stratified over the sun's cone (its radiance uniform)."""
    e = np.zeros((len(origins), 3))
    for light in lights:
        d, _, irr = light.towards(origins.astype(np.float64))
        cos = np.maximum((normals * d).sum(axis=1), 0)
        seen = ~scene.occluded(origins, d.astype(np.float32), None)
        e += irr * (cos * seen)[:, None]
    side = int(np.sqrt(rays))
    u = (np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) + 0.5) / side
    cones = sample_uniform_cone(u, np.asarray(sun.direction), np.cos(np.radians(sun.radius)))
    radiance = np.asarray(sun.irradiance) / (np.pi * np.sin(np.radians(sun.radius)) ** 2)
    solid = 2 * np.pi * (1 - np.cos(np.radians(sun.radius))) / len(cones)
    for d in cones:
        cos = np.maximum(normals @ d, 0)
        dirs = np.broadcast_to(d.astype(np.float32), origins.shape)
        seen = ~scene.occluded(origins, np.ascontiguousarray(dirs), None)
        e += radiance * (cos * seen * solid)[:, None]
    return e


def test_split_lattice_misses_exactly_the_first_vertex_direct_light(engine_starts):
    """The same paths with and without the split differ only at their first vertex (the
    continuation directions do not depend on the light samples), by the direct irradiance
    of the light and the sun: their mean difference per point matches shadow rays cast
    here, within the first vertex's own noise. The bounces keep the sun's light."""
    samples = 64
    scene, origins, normals, keys, _, settings = _paths(engine_starts, samples)
    env = "sky:zenith=0.2,horizon=0.3,ground=0.1,sun=4,sun_az=30,sun_el=35,sun_radius=2"
    lights = ("dir:0.3,-0.5,0.8:1.5,1.2,1.0",)
    full = trace_paths(scene, origins, normals, keys, _lighting(env, lights), settings)
    split = trace_paths(scene, origins, normals, keys, _lighting(env, lights, True), settings)
    points = len(engine_starts[1])
    difference = (full - split).reshape(points, samples, 3)
    sun = Lighting.parse(env, ()).pixel_lights()[0]
    want = _direct_irradiance(scene, engine_starts[1], engine_starts[2],
                              [parse_light(s) for s in lights], sun)
    mean = difference.mean(axis=1)
    stderr = difference.std(axis=1) / np.sqrt(samples)
    # the shadow rays above are stratified over the cone (256): their own error is small
    # against the paths' (one light sample per path); 5 standard errors per point and
    # channel, plus the quadrature's few per mille of the sun's irradiance
    z = np.abs(mean - want) / (stderr + 0.004 * 4 + 1e-9)
    assert np.mean(z < 5) > 0.995, np.sort(z.ravel())[-10:]
    assert abs(mean.sum() / want.sum() - 1) < 0.01
    assert want[:, 0].min() == 0 and want[:, 0].max() > 4  # shadowed and lit points
    # the split keeps the sun's and the light's bounces: a sky without sun and light
    # gives less light than the split
    no_direct = trace_paths(scene, origins, normals, keys,
                            _lighting("sky:zenith=0.2,horizon=0.3,ground=0.1"), settings)
    assert split.mean() > 1.05 * no_direct.mean()


def test_split_whole_paths_equal_the_vertex_by_vertex_tracer(engine_starts):
    """The compiled chunk call and the vertex-by-vertex tracer give the same sums to the
    bit with the sun split off, as they do without."""
    scene, origins, normals, vol = engine_starts
    assert scene.calls is not None
    samples = 24
    pos = np.repeat(np.arange(len(origins)), samples)
    sample = np.tile(np.arange(samples), len(origins))
    ids = np.arange(len(origins)) * 7 + 3
    starts = (np.uint32(rng.seed_key(5)), ids, pos, sample, np.arange(len(origins)),
              origins, normals)
    settings = PathSettings(bounces=2, albedo=(0.7, 0.6, 0.5),
                            hit_offset=2e-3 * float(min(vol.spacing)))
    weights = np.array([0.2126, 0.7152, 0.0722])
    results = []
    for pixel_direct in (True, False):
        lighting = _lighting("sky:sun=3,sun_el=25", (), pixel_direct)
        whole = whole_paths(lighting, settings)
        assert whole is not None
        acc = [np.zeros((len(origins), 3)), np.zeros(len(origins)),
               np.zeros(len(origins), np.int64)]
        trace_whole_paths(scene, whole, starts, weights, _Sums(*acc))
        keys, o, n, d = kernels.path_starts(*starts)
        step = [np.zeros((len(origins), 3)), np.zeros(len(origins)),
                np.zeros(len(origins), np.int64)]
        est = trace_paths(scene, o.T, n.T, keys, lighting, settings, None, d.T)
        kernels.accumulate(pos, est, weights, *step)
        for a, b in zip(acc, step, strict=True):
            np.testing.assert_array_equal(a, b)
        results.append(acc[0])
    assert results[0].sum() < 0.8 * results[1].sum()  # the split took the sun's direct light


@dataclasses.dataclass
class _Sums:
    sum: np.ndarray
    second: np.ndarray
    n: np.ndarray


def test_sunless_sky_parameters_are_those_of_the_sky_without_sun():
    for spec in ("sky:sun=3", "sky:sun=5,sun_el=10,sun_radius=2,horizon_blur=0"):
        sky = parse_env(spec)
        np.testing.assert_array_equal(sky_kernels.sky_without_sun(sky_kernels.sky_params(sky)),
                                      sky_kernels.sky_params(sky.without_sun()))


# -- the renderer's shadows ---------------------------------------------------------------
HEIGHT = 1.5
"""Height of the occluders' centres above the plane z = 0."""


def _disc(centre, radius: float, n: int = 256):
    """(vertices, normals, faces) of a horizontal disc (a triangle fan)."""
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], 1) * radius
    vertices = np.vstack([[0, 0, 0], rim]) + np.asarray(centre)
    faces = np.stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n], 1)
    return vertices, np.tile([0.0, 0.0, 1.0], (n + 1, 1)), faces


def _visible_fraction(points, occluder: str, radius: float, sun: np.ndarray, tan_r: float,
                      rays: int = 1024) -> np.ndarray:
    """(N,) cosine-weighted fraction of the sun's cone seen from points on the plane z = 0
    (normal +z) past a disc or sphere of `radius` centred at (0, 0, HEIGHT): quadrature over
    the cone (stratified), exact intersections."""
    side = int(np.sqrt(rays))
    u = (np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) + 0.5) / side
    dirs = sample_uniform_cone(u, sun, np.cos(np.arctan(tan_r))) if tan_r > 0 else sun[None]
    centre = np.array([0.0, 0.0, HEIGHT])
    seen = np.zeros(len(points))
    for d in dirs:
        to_c = centre - points
        if occluder == "disc":
            t = to_c[:, 2] / d[2]
            q = points + t[:, None] * d
            blocked = np.hypot(q[:, 0], q[:, 1]) <= radius
        else:
            along = to_c @ d
            blocked = (along > 0) & (np.linalg.norm(to_c - along[:, None] * d, axis=1)
                                     <= radius)
        seen += d[2] * ~blocked
    return seen / dirs[:, 2].sum()


def _zero_lattice(lo, hi):
    geometry = LatticeGeometry((4, 4, 4), tuple(lo), tuple(hi))
    shape = geometry.shape
    return Lattice(geometry, np.zeros((*shape, 3), np.float32), np.ones(shape, np.uint32),
                   np.zeros(shape, np.float32), np.ones(shape, bool), {"kind": "irradiance"})


def _plane_visibility(renderer, occluder: str, light, size=(160, 160)):
    """Rendered and analytic visibility of the light on the plane around the shadow, and
    the plane pixels' world positions."""
    radius = 0.5
    shape = _disc((0, 0, HEIGHT), radius) if occluder == "disc" else _sphere(
        (0, 0, HEIGHT), radius, 48, 96)
    renderer.set_mesh(*_merge(_plane(0.0, 3.5, 2), shape))
    lo, hi = np.array([-3.5, -3.5, -0.1]), np.array([3.5, 3.5, HEIGHT + 0.6])
    renderer.set_bounds(lo, hi)
    renderer.set_lattice(_zero_lattice(lo, hi))
    sun = np.asarray(light.direction)
    target = -HEIGHT * sun / sun[2]  # the occluder's shadow centre
    # seen from above the shadow, high enough that the occluder hides none of it
    camera = Camera(azimuth=0, elevation=90, distance=2.8, target=tuple(target), scale=1.6)
    base = RenderSettings(size=size, tonemap="clamp", albedo=(1, 1, 1))
    points, mask = _render(renderer, camera, dataclasses.replace(base, shading="position"))
    lit, _ = _render(renderer, camera, dataclasses.replace(
        base, shading="irradiance", direct_lights=(light,)))
    plane = mask & (np.abs(points[..., 2]) < 1e-4)
    e = np.asarray(light.irradiance)[0] * sun[2]
    rendered = lit[plane][:, 0] * np.pi / e
    tan_r = np.tan(np.radians(light.radius)) if isinstance(light, SunLight) else 0.0
    exact = _visible_fraction(points[plane], occluder, radius, sun, tan_r)
    texel = 2 * 1.01 * np.linalg.norm(hi - lo) / 2 / 2048
    return rendered, exact, points[plane], texel


def _render(renderer, camera, settings):
    frame = renderer.render(camera, settings)
    return frame.linear.astype(np.float64), frame.mask


def _edge_widths(points, values, sun):
    """Umbra and penumbra widths of a round shadow along the sun's azimuth (world units):
    the extent of values < 0.05 and twice the mean extent of 0.05 ≤ values ≤ 0.95."""
    horizontal = sun[:2] / np.linalg.norm(sun[:2])
    across = points[:, :2] @ np.array([-horizontal[1], horizontal[0]])
    line = np.abs(across) < 0.02
    along = points[line, :2] @ horizontal
    v = values[line]
    umbra = np.ptp(along[v < 0.05]) if (v < 0.05).any() else 0.0
    penumbra = np.ptp(along[(v >= 0.05) & (v <= 0.95)]) - umbra
    return umbra, penumbra


SUN = np.array([1.0, 0.3, 1.0]) / np.linalg.norm([1.0, 0.3, 1.0])


@pytest.mark.parametrize("occluder", ["disc", "sphere"])
def test_hard_shadow_of_a_directional_light_matches_the_analytic_one(renderer, occluder):
    light = DirectionalLight(tuple(SUN), (2.0, 2.0, 2.0))
    rendered, exact, points, texel = _plane_visibility(renderer, occluder, light)
    umbra = exact == 0
    assert 2000 < umbra.sum() < 0.6 * len(exact)
    # away from the edge by the filter's reach (1 texel + bilinear 1.5 texels, across a
    # plane stretched by 1/cos of the light's angle) and a pixel, exact; no acne on the
    # lit plane, no light leaking under the caster
    pixel = 1.6 * 2.8 * 2 * np.tan(np.radians(15)) / 160
    near_edge = _distance_to_edge(points, exact) < 2.5 * texel / SUN[2] + pixel
    np.testing.assert_allclose(rendered[umbra & ~near_edge], 0, atol=1e-5)
    np.testing.assert_allclose(rendered[~umbra & ~near_edge], 1, atol=1e-5)
    assert (umbra & ~near_edge).sum() > 1000 and (~umbra & ~near_edge).sum() > 10_000


def _distance_to_edge(points, visible):
    """(N,) distance from each point to the nearest point of the other kind (lit/shadowed),
    brute force over a subsample of the other kind."""
    from scipy.spatial import cKDTree

    lit = visible > 0.5
    out = np.empty(len(points))
    for kind in (True, False):
        other = points[lit != kind][:, :2]
        tree = cKDTree(other)
        out[lit == kind] = tree.query(points[lit == kind][:, :2])[0]
    return out


@pytest.mark.parametrize("occluder", ["disc", "sphere"])
def test_soft_sun_shadow_matches_the_analytic_penumbra(renderer, occluder):
    """A sun of 3° angular radius: the visible fraction of its disc, per plane pixel,
    against quadrature over its cone; umbra and penumbra widths along the sun's azimuth."""
    sun = SunLight(tuple(SUN), (2.0, 2.0, 2.0), 3.0)
    rendered, exact, points, _ = _plane_visibility(renderer, occluder, sun)
    penumbra = (exact > 0.02) & (exact < 0.98)
    assert penumbra.sum() > 1000
    error = np.abs(rendered - exact)
    # PCSS with 16 taps over the penumbra disc, turned per pixel: per-pixel noise of a few
    # per cent (16 bilinear comparisons, measured 3.1 % mean, 0.03 % bias on the disc's
    # penumbra); a disc occluder lies at one depth, where the blocker estimate is exact;
    # a sphere's blockers span its lower half, and their mean depth lies above its
    # silhouette (measured: 4.1 % mean error, the penumbra 9 % wider)
    limit = 0.04 if occluder == "disc" else 0.05
    assert np.mean(error[penumbra]) < limit
    assert abs(np.mean((rendered - exact)[penumbra])) < limit / 4  # no bias
    got, want = _edge_widths(points, rendered, SUN), _edge_widths(points, exact, SUN)
    assert abs(got[0] - want[0]) < 0.05 * want[0]  # umbra
    assert 0.9 * want[1] < got[1] < (1.15 if occluder == "disc" else 1.25) * want[1]
    # away from the penumbra: exactly lit (no acne) and exactly dark (no leaks)
    far_lit = (exact > 0.9999) & (_distance_to_edge(points, exact > 0.9999) > 0.1)
    far_dark = (exact < 1e-4) & (_distance_to_edge(points, exact > 1e-4) > 0.1)
    assert far_lit.sum() > 5000 and far_dark.sum() > 1000
    np.testing.assert_allclose(rendered[far_lit], 1, atol=1e-5)
    np.testing.assert_allclose(rendered[far_dark], 0, atol=1e-5)


def test_point_light_shadow_matches_ray_cast_visibility(renderer):
    """A point light's six shadow faces: the plane under a sphere, against exact rays."""
    position = np.array([0.4, -0.3, 3.0])
    light = PointLight(tuple(position), (5.0, 5.0, 5.0))
    renderer.set_mesh(*_merge(_plane(0.0, 3.5, 2), _sphere((0, 0, HEIGHT), 0.5, 48, 96)))
    lo, hi = np.array([-3.5, -3.5, -0.1]), np.array([3.5, 3.5, 3.2])
    renderer.set_bounds(lo, hi)
    renderer.set_lattice(_zero_lattice(lo, hi))
    camera = Camera(azimuth=0, elevation=90, distance=1.0, target=(-0.3, 0.25, 0), scale=2.5)
    base = RenderSettings(size=(160, 160), tonemap="clamp", albedo=(1, 1, 1))
    points, mask = _render(renderer, camera, dataclasses.replace(base, shading="position"))
    lit, _ = _render(renderer, camera, dataclasses.replace(
        base, shading="irradiance", direct_lights=(light,)))
    plane = mask & (np.abs(points[..., 2]) < 1e-4)
    p = points[plane]
    to_light = position - p
    r2 = (to_light**2).sum(axis=1)
    d = to_light / np.sqrt(r2)[:, None]
    to_c = np.array([0, 0, HEIGHT]) - p
    along = (to_c * d).sum(axis=1)
    blocked = (along > 0) & (np.linalg.norm(to_c - along[:, None] * d, axis=1) <= 0.5)
    want = 5.0 * d[:, 2] / r2 * ~blocked
    got = lit[plane][:, 0] * np.pi
    assert blocked.mean() > 0.05
    wrong = np.abs(got - want) > 0.02 * want.max()
    assert wrong.mean() < 0.01  # the shadow's edge pixels only


@pytest.mark.parametrize("towards", [(0.3, -0.5, 0.8), (0.2, -0.8, -0.5)])
def test_deferred_pass_keeps_the_normals_a_sphere_follows_the_cosine_law(renderer, towards):
    """The lattice and the lights are shaded from the G-buffer (octahedral normals): on a
    sphere under a lattice of constant E and a directional light, every surface pixel shows
    albedo (E + E_l max(n.l, 0)) / pi with n the sphere's normal there, lit from above and
    from below (both halves of the octahedral map), in all four quadrants of the view."""
    light = DirectionalLight(towards, (2.0, 1.5, 1.0))
    towards_light = np.asarray(light.direction)
    renderer.set_mesh(*_merge(_sphere((0, 0, 0), 1.0, 96, 192)))
    lo, hi = np.full(3, -1.2), np.full(3, 1.2)
    renderer.set_bounds(lo, hi)
    lattice = _zero_lattice(lo, hi)
    lattice.values[...] = 0.3
    renderer.set_lattice(lattice)
    camera = Camera(azimuth=35, elevation=0, distance=1.5, target=(0, 0, 0), scale=2.4)
    base = RenderSettings(size=(128, 128), tonemap="clamp", albedo=(0.8, 0.7, 0.6))
    points, mask = _render(renderer, camera, dataclasses.replace(base, shading="position"))
    shown, shown_mask = _render(renderer, camera, dataclasses.replace(
        base, shading="irradiance", direct_lights=(light,)))
    assert (mask == shown_mask).all() and mask.mean() > 0.3
    n = points[mask] / np.linalg.norm(points[mask], axis=1, keepdims=True)
    cosine = n @ towards_light
    want = np.asarray(base.albedo) * (0.3 + np.asarray(light.irradiance)
                                      * np.maximum(cosine, 0)[:, None]) / np.pi
    # away from the terminator, where the shadow map's own edge lies; elsewhere the mesh's
    # interpolated normals differ from the sphere's by < 1e-3 (96 x 192 facets)
    lit, dark = cosine > 0.15, cosine < -0.05
    np.testing.assert_allclose(shown[mask][lit | dark], want[lit | dark], rtol=3e-3)
    for side in (n[:, 2] > 0.4, n[:, 2] < -0.4):  # both halves of the octahedral map
        assert (lit & side).sum() > 100
    assert dark.sum() > 100


def test_split_sh_sun_is_the_same_whether_the_transfer_is_deferred_or_not(renderer):
    """A split SH transfer of order 3 is read in the deferred pass; one of order 5 needs
    13 textures, too many beside the G-buffer and the shadow atlas, and is read in the
    surface pass, which then writes the G-buffer for the sun alone. With a zero transfer
    both pictures are the sun's direct light alone, and the same (before, order 5 with the
    sun drew nothing: its textures and the atlas shared a texture unit)."""
    from isolume.baking import sh

    vol = volumes.load("synthetic:engine:40")
    mesh = volumes.isosurface(vol, 0.3)
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=0.3)
    renderer.set_bounds(*vol.box)
    camera = Camera(azimuth=200, elevation=35, distance=1.6,
                    target=tuple(np.mean(vol.box, axis=0)), scale=vol.diagonal)
    settings = RenderSettings(size=(96, 96), shading="sh", tonemap="clamp",
                              env_rotation=(160.0, 0.0))
    pictures, deferred = [], []
    for order in (3, 5):
        config = BakeConfig(mode="sh", sh_order=order, env="sky:sun=3", direct_light="pixels")
        meta = {"kind": "sh", "sh_order": order}
        lattice = Lattice.empty(LatticeGeometry.for_volume(vol, 0.5), 2 * order * order, meta,
                                config=config)
        lattice.samples[...] = 1  # computed, and zero
        renderer.set_lattice(lattice)
        renderer.set_environment(sh.display_coefficients(parse_env("sky:sun=3"), order,
                                                         blocks=2))
        deferred.append(renderer._lattice_deferred(settings))
        pictures.append(_render(renderer, camera, settings))
    assert deferred == [True, False]
    (low, low_mask), (high, high_mask) = pictures
    assert (low_mask == high_mask).all() and low_mask.mean() > 0.2
    sun = low[low_mask].max(axis=1)
    assert (sun > 0.05).mean() > 0.2 and (sun < 1e-6).mean() > 0.2  # lit and unlit parts
    np.testing.assert_allclose(high, low, atol=1e-6)


def test_bench_frames_times_the_sun_per_pixel_beside_phong_shadow():
    """`isolume bench frames` times irradiance with the sun per pixel in the same
    interleaved rounds as the local modes and reports its ratios (wall and CPU time)."""
    from isolume.app.bench.view import DIRECT_MODE, frame_times

    vol = volumes.load("synthetic:sphere:16")
    r = frame_times(vol, 0.5, (32, 32), frames=2, backend="osmesa", rounds=2)
    assert r["rounds"] == 2 and {"phong_shadow", "irradiance", DIRECT_MODE} <= set(r["modes"])
    for f in r["modes"].values():
        assert f["ms"] > 0 and f["cpu_ms"] > 0
    assert r["cpu_ratios"][f"{DIRECT_MODE}/phong_shadow"] > 0
    assert r["ratios"][f"{DIRECT_MODE}/phong_shadow"] == pytest.approx(
        r["modes"][DIRECT_MODE]["ms"] / r["modes"]["phong_shadow"]["ms"])


# -- the renderer reads the lattice's setting ---------------------------------------------
def test_lattice_direct_lights_follow_the_bake_setting():
    config = BakeConfig(env="sky:sun=3", lights=("dir:0,0,1:1,1,1",))
    lattice = _zero_lattice((0, 0, 0), (1, 1, 1))
    lattice.meta["kind"], lattice.config = "irradiance", config
    lights = lattice_direct_lights(lattice)
    assert len(lights) == 2 and isinstance(lights[1], SunLight)
    lattice.config = dataclasses.replace(config, direct_light="lattice")
    assert lattice_direct_lights(lattice) == ()
    old = config.to_dict()
    del old["direct_light"]  # a file from before the setting
    lattice.config = BakeConfig.from_dict(old)
    assert lattice_direct_lights(lattice) == ()


def test_too_many_per_pixel_lights_are_refused():
    assert direct_tiles([PointLight((0, 0, 0), (1, 1, 1)), SunLight((0, 0, 1), (1, 1, 1), 1)]
                        ) == [0, 6]
    with pytest.raises(RenderError, match="at most"):
        RenderSettings(direct_lights=(PointLight((0, 0, 0), (1, 1, 1)),) * 3)
    with pytest.raises(RenderError, match="expected a PointLight"):
        RenderSettings(direct_lights=("dir:0,0,1:1,1,1",))


def _engine_in_the_sun(renderer):
    """The synthetic engine (64³) at iso 0.3 in `renderer`, with a lattice of no light of
    its own that leaves the sun to the pixels (no sky, no bounces): (volume, mesh, the
    lattice's config, a camera on its fins and bores)."""
    from isolume.baking.lattice import volume_identity

    vol = volumes.load("synthetic:engine:64")
    mesh = volumes.isosurface(vol, 0.3)
    renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=0.3)
    renderer.set_bounds(*vol.box)
    config = BakeConfig(samples=256, bounces=0, env="sky:zenith=0,horizon=0,ground=0,sun=3",
                        direct_light="pixels")
    lattice = Lattice.empty(LatticeGeometry.for_volume(vol, 0.25), 3,
                            {"kind": "irradiance", "volume": volume_identity(vol)},
                            config=config)
    lattice.samples[...] = 1  # no light of its own: only the sun, per pixel
    renderer.set_lattice(lattice)
    camera = Camera(azimuth=200, elevation=35, distance=1.6,
                    target=tuple(np.mean(vol.box, axis=0)), scale=vol.diagonal)
    return vol, mesh, config, camera


def test_sun_on_an_isosurface_matches_ray_cast_shadows(renderer):
    """The sun alone (no sky, no bounces) on the synthetic engine's fins and bores, shaded
    per pixel, against the reference tracer's shadow rays over the sun's disc at the same
    pixels (its start points lifted by the bake's offset, as the renderer's lookups)."""
    from isolume.baking.reference import render_reference

    vol, _, config, camera = _engine_in_the_sun(renderer)
    size = (128, 128)
    frame = renderer.render(camera, RenderSettings(size=size, shading="irradiance"))
    ref, _ = render_reference(vol, 0.3, *camera.primary_rays(*size), config, workers=2)
    both = frame.mask.reshape(-1) & ref.mask
    got = frame.linear.reshape(-1, 3)[both, 0].astype(np.float64)
    want, stderr = ref.radiance[both, 0], ref.stderr[both, 0]
    lit = want > 0.5 * want.max()
    assert 0.2 < lit.mean() < 0.9 and (want < 0.01 * want.max()).mean() > 0.05
    # pixels off by more than the reference's noise allows: shadow-edge pixels and the few
    # where the mesh's interpolated normal and the volume's gradient disagree about facing
    # the sun (sharp edges); acne or leaks would cover whole surfaces
    off = np.abs(got - want) > 5 * stderr + 0.05 * want.max()
    assert off.mean() < 0.005, off.mean()  # measured 0.03 %
    assert abs(got.mean() / want.mean() - 1) < 0.01  # neither darker (acne) nor brighter


def test_the_g_buffer_gives_the_traced_sun_the_surface_a_position_pass_gives(renderer):
    """A frame's own G-buffer stands in for a position pass (a movie frame's traced sun,
    `SurfaceRenderer.render(..., seen=)`): the same pixels, their points within 1e-5 of
    the box's diagonal (an eye distance against an interpolated position), and the same
    picture, traced from either."""
    from isolume.app.render.traced_light import position_pass, trace_direct_light

    vol, mesh, _, camera = _engine_in_the_sun(renderer)
    settings = RenderSettings(size=(96, 80), shading="irradiance", auto_exposure=False)
    scene = Scene(mesh.vertices, mesh.faces)

    def traced(seen):
        trace_direct_light(renderer, camera, settings, vol, seen, scene, workers=2)

    points, mask = position_pass(renderer, camera, settings)
    traced((points, mask))
    passed = renderer.render(camera, settings)
    found = []
    own = renderer.render(camera, settings, seen=lambda seen: (found.append(seen), traced(seen)))
    (g_points, g_mask), = found
    np.testing.assert_array_equal(g_mask, mask)
    assert 0.2 < mask.mean() < 0.9
    assert np.abs(g_points - points).max() < 1e-5 * vol.diagonal
    np.testing.assert_array_equal(own.mask, passed.mask)
    assert np.abs(own.linear - passed.linear).max() <= 1e-6 * passed.linear.max()


# -- the viewer moves the sun ---------------------------------------------------------------
def test_viewer_moves_the_sun_with_exact_shadows(display, tmp_path):  # noqa: F811
    """A lattice whose sun is shaded per pixel: turning the light in the viewer moves the
    sun's light and shadows (the lattice's part of the picture stays), "light camera" puts
    it back where it was baked."""
    from isolume.baking.lazy import new_lattice

    vol = volumes.load("synthetic:engine:48")
    config = BakeConfig(env="sky:sun=3", samples=1)
    lattice = new_lattice(vol, config)
    lattice.values[...] = 0.4
    lattice.samples[...] = 1
    lattice.active[...] = True
    lattice.save(tmp_path / "sun.npz")
    (tmp_path / "s.txt").write_text("wait-mesh\nscreenshot baked.png\nlight 20 25\n"
                                    "screenshot moved.png\nlight camera\n"
                                    "screenshot back.png\nquit\n")
    run = _view(["synthetic:engine:48", "--lattice", "sun.npz", "--no-bake", "--shading",
                 "irradiance", "--size", "320x240", "--script", "s.txt"],
                display, tmp_path)
    assert run.returncode == 0, run.stderr
    baked, mask = _surface(tmp_path / "baked.exr")
    moved, moved_mask = _surface(tmp_path / "moved.exr")
    back, _ = _surface(tmp_path / "back.exr")
    assert (mask == moved_mask).all()
    lattice_only = 0.8 * 0.4 / np.pi  # albedo · E / π of the lattice's constant E
    # baked, the sun (az 45°, el 40°) leaves the faces the camera sees in shadow; turned
    # towards the camera it lights them: the sun moved, the lattice's light stayed
    in_shadow = baked[mask][:, 0] < lattice_only + 0.01
    lit_now = moved[mask][:, 0] > lattice_only + 0.1
    assert in_shadow.mean() > 0.3 and (in_shadow & lit_now).mean() > 0.3
    assert min(moved[mask].min(), baked[mask].min()) >= lattice_only - 1e-3
    np.testing.assert_allclose(back, baked, atol=1e-6)


def test_viewer_light_note_says_when_the_bounced_light_is_stale(gl):
    from isolume.app.viewer.draw import Drawing, ViewState
    from isolume.app.viewer.panel import direction_from_angles
    from isolume.baking.lazy import new_lattice

    vol = volumes.load("synthetic:sphere:16")
    config = BakeConfig(env="sky:sun=3,sun_az=45,sun_el=40", samples=1)
    lattice = new_lattice(vol, config)
    drawing = Drawing(gl, vol, auto_exposure=False)
    try:
        assert drawing.show_lattice(lattice) is None
        state = ViewState(iso=0.5, shading="irradiance", exposure=1.0)
        assert "shaded per pixel" in drawing.light_note(state)
        sun = Lighting.parse(config.env, ()).pixel_lights()[0]
        start = drawing.light_angles(state, None)  # the drag starts at the baked sun
        np.testing.assert_allclose(direction_from_angles(*start), sun.direction, atol=1e-9)
        state.light = (start[0] + 30.0, start[1])
        assert "stale" in drawing.light_note(state)
        (moved,) = drawing.settings(state, (8, 8)).direct_lights
        assert moved.radius == sun.radius and moved.irradiance == sun.irradiance
        state.shading = "phong_hemi"
        assert drawing.light_note(state) is None
    finally:
        drawing.release()


def test_several_lights_add_up(renderer):
    """Each light is one call of the specialised shader (`direct_sum`); together they
    give the sum of their pictures (the lattice's light counted once)."""
    from isolume.app.render.lights import direct_sum

    sun = SunLight(tuple(SUN), (2.0, 2.0, 2.0), 3.0)
    hard = DirectionalLight((-0.3, 0.4, 0.8), (1.0, 0.5, 0.25))
    point = PointLight((0.5, -0.4, 3.0), (4.0, 4.0, 4.0))
    assert direct_sum((hard, sun, point)) == ("(distant_hard(0, 0, p, n, f) + distant_soft"
                                              "(1, 1, p, n, f) + point_light(2, 2, p, n, f))")
    renderer.set_mesh(*_merge(_plane(0.0, 3.5, 2), _sphere((0, 0, HEIGHT), 0.5, 48, 96)))
    lo, hi = np.array([-3.5, -3.5, -0.1]), np.array([3.5, 3.5, 3.2])
    renderer.set_bounds(lo, hi)
    lattice = _zero_lattice(lo, hi)
    lattice.values[...] = 0.3
    renderer.set_lattice(lattice)
    camera = Camera(azimuth=30, elevation=60, distance=1.0, target=(0, 0, 0.5), scale=5.0)
    base = RenderSettings(size=(96, 96), tonemap="clamp", shading="irradiance")
    pictures = [_render(renderer, camera, dataclasses.replace(base, direct_lights=lights))[0]
                for lights in [(hard, sun, point), (hard,), (sun,), (point,), ()]]
    together, *alone, none = pictures
    # the per-pixel turn of the sun's taps depends only on the pixel: the same noise
    np.testing.assert_allclose(together, sum(alone) - 2 * none, rtol=1e-4, atol=2e-5)
    assert (together - none).max() > 0.1
