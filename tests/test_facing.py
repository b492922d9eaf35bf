"""The side-aware lattice lookup: each texel's facing (the mean direction its paths started
along) keeps light gathered on one face of a thin wall, rod or sheet off the other face.

Phantoms are anti-aliased slabs and rods (each voxel holds the fraction of it inside the
solid), lit from above by a directional light; E is looked up at the vertices of the
half-maximum isosurface with their normals (pointing out of the solid: towards any eye
outside it), at 1 texel per voxel.
"""

import json

import numpy as np
import pytest
from test_render_modes import _filtered_atol, _plane, _positions, _render

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.settings import RenderSettings
from isolume.baking import BakeConfig, Lattice, bake, octahedral
from isolume.baking.lattice import LatticeGeometry, trilinear, trilinear_corners
from isolume.baking.sided import SIDE_BLEND, side_weights
from isolume.volumes import Volume

SIZE = 20
H = 1.0 / SIZE
AXIS = (np.arange(SIZE) - (SIZE - 1) / 2) * H


def _volume(data: np.ndarray, name: str) -> Volume:
    return Volume(np.ascontiguousarray(data, np.float32), (H, H, H), (AXIS[0],) * 3,
                  name=name, source=name)


def _plate(thickness: float, offset: float) -> Volume:
    """A horizontal slab `thickness` voxels thick, its middle `offset` voxels above a
    voxel centre."""
    lo, hi = (offset - thickness / 2) * H, (offset + thickness / 2) * H
    z = AXIS[:, None, None]
    cover = np.clip(np.minimum(z + H / 2, hi) - np.maximum(z - H / 2, lo), 0, None) / H
    return _volume(np.broadcast_to(cover, (SIZE,) * 3), "plate")


def _rod(diameter: float, offset: float, sub: int = 4) -> Volume:
    """A rod along x, `diameter` voxels thick, its axis `offset` voxels off a voxel centre
    in y and z (coverage from sub × sub points per voxel)."""
    s = AXIS[:, None] + ((np.arange(sub) + 0.5) / sub - 0.5)[None, :] * H - offset * H
    inside = s[:, None, :, None] ** 2 + s[None, :, None, :] ** 2 <= (diameter * H / 2) ** 2
    cover = inside.mean(axis=(2, 3))  # (y, z)
    return _volume(np.broadcast_to(cover.T[:, :, None], (SIZE,) * 3), "rod")


def _bake_from_above(vol: Volume, bounces: int = 0, workers: int = 2) -> Lattice:
    top = vol.value_range[1]
    config = BakeConfig(samples=2 if bounces == 0 else 16, bounces=bounces, env="",
                        lights=("dir:0,0,1:1,1,1",), direct_light="lattice",
                        iso_range=(0.4 * top, 0.6 * top))
    return bake(vol, config, workers=workers)


def _faces(vol: Volume, lattice: Lattice) -> dict:
    """Mean E/E0 on the lit (normal up) and the unlit (normal down) faces, looked up plain
    and side-aware."""
    mesh = volumes.isosurface(vol, 0.5 * vol.value_range[1])
    inner = (np.abs(mesh.vertices[:, 0]) < 0.3) & (np.abs(mesh.vertices[:, 1]) < 0.3)
    up, down = inner & (mesh.normals[:, 2] > 0.5), inner & (mesh.normals[:, 2] < -0.5)
    out = {}
    for name, normals in (("plain", None), ("sided", mesh.normals)):
        e = lattice.sample(mesh.vertices, normalized=True, normals=normals)[:, 0]
        out[name] = (e[up].mean(), e[down].mean())
    return out


def surface_normals(mesh, points: np.ndarray, eye: np.ndarray, k: int = 16) -> np.ndarray:
    """(N, 3) the shading normals the surface pass interpolates at (N, 3) points on `mesh`
    (its vertex normals, barycentric in the triangle holding the point: one of the `k`
    with the nearest centroids), normalised and turned towards `eye` as ``surface.frag``
    turns them."""
    from scipy.spatial import cKDTree

    tri = mesh.vertices[mesh.faces].astype(np.float64)  # (F, 3, 3)
    _, near = cKDTree(tri.mean(axis=1)).query(points, k=k)  # (N, k)
    a, e1, e2 = tri[near, 0], tri[near, 1] - tri[near, 0], tri[near, 2] - tri[near, 0]
    d = points[:, None, :] - a
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    p1, p2 = (d * e1).sum(-1), (d * e2).sum(-1)
    den = d11 * d22 - d12**2
    v, w = (d22 * p1 - d12 * p2) / den, (d11 * p2 - d12 * p1) / den
    bary = np.stack([1 - v - w, v, w], axis=-1)  # (N, k, 3)
    facet = np.cross(e1, e2)
    facet /= np.linalg.norm(facet, axis=-1, keepdims=True)
    score = np.abs((d * facet).sum(-1)) + 1e3 * np.maximum(-bary.min(-1), 0)
    rows, best = np.arange(len(points)), np.argmin(score, axis=1)
    corners = mesh.normals[mesh.faces[near[rows, best]]].astype(np.float64)  # (N, 3, 3)
    n = (bary[rows, best][:, :, None] * corners).sum(axis=1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(((np.asarray(eye) - points) * n).sum(1, keepdims=True) < 0, -n, n)


# -- the encoding ---------------------------------------------------------------------------
def test_octahedral_round_trip_within_two_thirds_of_a_degree():
    """Measured over 200k random directions: max 0.63°, mean 0.31°."""
    rng = np.random.default_rng(1)
    v = rng.normal(size=(200_000, 3))
    v = np.concatenate([v, np.eye(3), -np.eye(3), [[1e-4, 1e-4, -1.0]]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    codes = octahedral.encode(v)
    assert codes.dtype == np.uint8 and codes.shape == (len(v), 2)
    assert octahedral.known(codes).all()  # -z is not the unknown code
    error = np.degrees(np.arccos(np.clip((octahedral.decode(codes) * v).sum(1), -1, 1)))
    assert error.max() <= 0.65 and error.mean() <= 0.35
    # any length; nothing and non-finite vectors are unknown, and decode to nothing
    np.testing.assert_array_equal(octahedral.encode(3 * v[:5]), codes[:5])
    unknown = octahedral.encode(np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 1.0]]))
    np.testing.assert_array_equal(unknown, [octahedral.UNKNOWN] * 2)
    np.testing.assert_array_equal(octahedral.decode(unknown), 0.0)


def test_octahedral_codes_are_the_nearest_of_the_four_around_each_point():
    """Each code decodes (`decode`) at least as near its vector as the other three
    codes of the cell of the octahedral square its point falls in, folded lower half,
    borders and the axes included."""
    rng = np.random.default_rng(2)
    v = np.concatenate([rng.normal(size=(50_000, 3)), np.round(rng.normal(size=(5000, 3)), 1),
                        np.eye(3), -np.eye(3)])
    v = v[np.linalg.norm(v, axis=1) > 0]
    unit = v / np.abs(v).sum(axis=1, keepdims=True)
    fold = (1 - np.abs(unit[:, 1::-1])) * np.where(unit[:, :2] >= 0, 1.0, -1.0)
    p = np.where(unit[:, 2:] < 0, fold, unit[:, :2])
    base = np.floor((p + 1) * 127.5)
    nearest = np.full(len(v), -np.inf)
    for step in ((0, 0), (0, 1), (1, 0), (1, 1)):
        codes = np.clip(base + step, 0, 255).astype(np.uint8)
        codes[(codes == 0).all(axis=1)] = 255  # the corner −z (0, 0) is stored as (255, 255)
        nearest = np.maximum(nearest, (octahedral.decode(codes) * v).sum(axis=1))
    chosen = (octahedral.decode(octahedral.encode(v)) * v).sum(axis=1)
    np.testing.assert_array_less(nearest - chosen, 1e-12 * np.linalg.norm(v, axis=1))

def test_compiled_side_weights_are_the_array_codes_bits():
    """`octahedral.side_rows` (the baker's compiled side weights, read through rows of a
    facing table) gives `side_weights`' bits for the square, unknown codes and rows −1
    (row 0) included, and other powers to within rounding."""
    rng = np.random.default_rng(5)
    codes = rng.integers(0, 256, (3000, 2)).astype(np.uint8)
    codes[::9] = 0
    for k in (1, 8, 26):
        rows = rng.integers(-1, len(codes), (4000, k))
        normals = rng.normal(size=(4000, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        looked_up = codes[np.maximum(rows, 0)]
        np.testing.assert_array_equal(octahedral.side_rows(rows, codes, normals, 2),
                                      side_weights(looked_up, normals, 2))
        np.testing.assert_allclose(octahedral.side_rows(rows, codes, normals, 3),
                                   side_weights(looked_up, normals, 3), rtol=0, atol=1e-15)


# -- the baker's facings ----------------------------------------------------------------------
def test_facings_are_the_start_normals_and_do_not_depend_on_the_workers():
    vol = _plate(1.0, 0.25)
    one, two = _bake_from_above(vol, workers=1), _bake_from_above(vol, workers=2)
    np.testing.assert_array_equal(one.facing, two.facing)
    np.testing.assert_array_equal(octahedral.known(one.facing), one.samples > 0)
    m = octahedral.decode(one.facing)[one.samples > 0]
    assert (np.abs(m[:, 2]) > 0.999).all()  # a slab's faces: straight up or down
    ups = (m[:, 2] > 0).sum()
    assert 0.3 < ups / len(m) < 0.7  # both faces have texels of their own


def test_facings_survive_a_file_and_old_files_load_without_them(tmp_path):
    lattice = _bake_from_above(_plate(1.0, 0.25))
    path = tmp_path / "plate.npz"
    lattice.save(path)
    np.testing.assert_array_equal(Lattice.load(path).facing, lattice.facing)
    old = tmp_path / "old.npz"  # format version 1, as written before facings were kept
    meta = dict(lattice.meta, format_version=1, shape=list(lattice.geometry.shape),
                box_lo=list(lattice.geometry.lo), box_hi=list(lattice.geometry.hi))
    np.savez_compressed(old, values=lattice.values, samples=lattice.samples,
                        second=lattice.second, active=lattice.active,
                        meta=np.array(json.dumps(meta)))
    loaded = Lattice.load(old)
    assert loaded.facing.shape == (*lattice.geometry.shape, 2) and not loaded.facing.any()
    assert not loaded.facing_known()
    points = lattice.geometry.centres(np.flatnonzero(lattice.samples))
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    np.testing.assert_array_equal(loaded.sample(points, normalized=True, normals=normals),
                                  lattice.sample(points, normalized=True))


# -- leaks ----------------------------------------------------------------------------------
@pytest.mark.parametrize("thickness", [0.6, 1.0, 2.0])
@pytest.mark.parametrize("offset", [0.25, 0.5])
def test_thin_plates_keep_the_light_on_the_lit_face(thickness, offset):
    """A slab lit from above: E/E0 is 1 on top, 0 underneath. The plain lookup mixes texels
    lit on the other face: measured (lit face, unlit face) 0.6 voxel thick (0.50, 0.00) at
    offset 0.25 and 0.5; 1 voxel (1.00, 0.25) at 0.25, (0.50, 0.00) at 0.5; 2 voxels
    (1.00, 0.00). Side-aware: (1.00, 0.00) for all."""
    vol = _plate(thickness, offset)
    faces = _faces(vol, _bake_from_above(vol))
    lit, unlit = faces["sided"]
    assert lit >= 0.95 and unlit <= 0.05 * lit
    plain_lit, plain_unlit = faces["plain"]
    if thickness < 2:  # the plain lookup leaks one way or the other
        assert plain_lit < 0.9 or plain_unlit > 0.2


def test_a_bounce_and_the_sun_keep_the_unlit_face_dark():
    """One bounce under a sun, 1 voxel thick: nothing else in the scene lights the
    underside. Measured E (lit, unlit): plain (3.20, 0.80), side-aware (3.20, 0.00)."""
    vol = _plate(1.0, 0.25)
    top = vol.value_range[1]
    config = BakeConfig(samples=8, bounces=1, env="sky:zenith=0,horizon=0,ground=0,sun=5",
                        direct_light="lattice", iso_range=(0.4 * top, 0.6 * top))
    faces = _faces(vol, bake(vol, config, workers=2))
    (lit, unlit), (_, plain_unlit) = faces["sided"], faces["plain"]
    assert unlit <= 0.05 * lit < plain_unlit


@pytest.mark.parametrize("diameter", [1.0, 1.5])
def test_a_thin_rod_shows_each_side_its_own_light(diameter):
    """A rod lit from above: E/E0 = max(0, n_z). Measured rms error over its surface
    (offset 0.25 voxel): plain 0.26 (1 voxel), 0.23 (1.5); side-aware 0.05, 0.11."""
    vol = _rod(diameter, 0.25)
    lattice = _bake_from_above(vol)
    mesh = volumes.isosurface(vol, 0.5 * vol.value_range[1])
    inner = np.abs(mesh.vertices[:, 0]) < 0.3
    ideal = np.maximum(mesh.normals[:, 2], 0)[inner]
    rms = {}
    for name, normals in (("plain", None), ("sided", mesh.normals)):
        e = lattice.sample(mesh.vertices, normalized=True, normals=normals)[inner, 0]
        rms[name] = np.sqrt(np.mean((e - ideal) ** 2))
    assert rms["sided"] < 0.6 * rms["plain"] and rms["sided"] < 0.13


# -- the shader against the CPU ---------------------------------------------------------------
def _random_lattice(channels: int = 3, kind: str = "irradiance", seed: int = 3) -> Lattice:
    """A 6³ lattice over [-1, 1]³ of random values and facings, a sixth not computed and
    a tenth of the facings unknown."""
    geometry = LatticeGeometry((6, 6, 6), (-1.0,) * 3, (1.0,) * 3)
    rng = np.random.default_rng(seed)
    values = rng.uniform(0.1, 1.0, (*geometry.shape, channels)).astype(np.float32)
    samples = (rng.random(geometry.shape) > 1 / 6).astype(np.uint32)
    facing = octahedral.encode(rng.normal(size=(*geometry.shape, 3)))
    facing[rng.random(geometry.shape) < 0.1] = 0
    meta = {"kind": kind, "sh_order": 2 if kind == "sh" else None}
    return Lattice(geometry, values, samples, np.zeros(geometry.shape, np.float32),
                   np.ones(geometry.shape, bool), meta, facing=facing)


def _plane_frames(renderer, lattice, elevation: float, **settings):
    """Radiance (albedo π: = E) of a tilted plane through the lattice seen from
    `elevation` degrees, the pixels' world points and their normals turned to the eye."""
    vertices, normals, faces = _plane(0.0, 0.9, n=8)
    tilt = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    vertices[:, 2] = -(vertices[:, :2] @ tilt[:2]) / tilt[2] + 0.05
    normals[:] = tilt
    renderer.set_mesh(vertices.astype(np.float32), normals.astype(np.float32),
                      faces.astype(np.uint32))
    renderer.set_bounds(np.full(3, -1.0), np.full(3, 1.0))
    renderer.set_lattice(lattice)
    camera = Camera(azimuth=30, elevation=elevation, distance=3.0, target=(0, 0, 0))
    size = (96, 96)
    radiance, mask = _render(renderer, camera, RenderSettings(
        size=size, tonemap="clamp", albedo=(np.pi,) * 3, **settings))
    points, _ = _positions(renderer, camera, size)
    points = points[mask]
    seen = np.where(((camera.eye - points) @ tilt)[:, None] > 0, tilt, -tilt)
    return radiance[mask], points, seen


def _sure(lattice: Lattice, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,) points away from where float32 may change the answer: cell boundaries, the
    ends of the blend into the plain mix, the blend with local shading (< 0.25 of computed
    weight)."""
    coords = lattice.geometry.to_texel_coords(points)
    idx, w = trilinear_corners(lattice.geometry.shape, coords)
    region = (idx[..., 0], idx[..., 1], idx[..., 2])
    w = w * lattice.shown(region)
    sided = (w * side_weights(lattice.displayed_facing(region), normals)).sum(1)
    ratio = np.divide(sided, w.sum(1), out=np.zeros(len(w)), where=w.sum(1) > 0)
    inside = np.clip(coords, 0, np.array(lattice.geometry.shape) - 1)
    near_boundary = (np.abs(inside - np.round(inside)) < 1e-3).any(axis=1)
    near_blend = (ratio < 1e-3) | (np.abs(ratio - SIDE_BLEND) < 1e-3)
    return (w.sum(1) > 0.27) & ~near_boundary & ~near_blend


@pytest.mark.parametrize("elevation", [50.0, -50.0])
def test_the_shader_looks_up_as_the_cpu_does(renderer, elevation):
    """Irradiance (LOOKUP 0): the GPU image equals `Lattice.sample` with the normals
    turned to the eye, within RGB9_E5 rounding, from either side of the plane."""
    lattice = _random_lattice()
    radiance, points, normals = _plane_frames(renderer, lattice, elevation,
                                              shading="irradiance")
    want = lattice.sample(points, normalized=True, normals=normals)
    plain = lattice.sample(points, normalized=True)
    sure = _sure(lattice, points, normals)
    assert sure.mean() > 0.8
    error = np.abs(radiance - want).max(axis=1)[sure]
    assert error.max() <= 2.0**-9 + 1e-5, error.max()
    assert np.abs(want - plain).max(axis=1)[sure].mean() > 0.05  # the sides mattered


def test_the_sh_lookup_is_side_aware_too(renderer):
    """SH transfer (order 2, gray; one texture): E = Σ τ_i ℓ_i of the side-aware mix of
    the texels' τ, as on the CPU, within float16 storage."""
    lattice = _random_lattice(channels=4, kind="sh")
    env = np.zeros((4, 3))
    env[:, 0], env[:, 1], env[:, 2] = [2.0, 0.5, -0.3, 0.8], [1.0, 0.2, 0.1, 0.0], 1.5
    renderer.set_lattice(lattice)
    renderer.set_environment(env)
    radiance, points, normals = _plane_frames(renderer, lattice, 50.0, shading="sh")
    tau = lattice.sample(points, normalized=True, normals=normals)
    want = np.maximum(tau @ env, 0)
    sure = _sure(lattice, points, normals)
    assert sure.mean() > 0.8
    scale = np.abs(env).sum(axis=0).max()
    assert np.abs(radiance - want).max(axis=1)[sure].max() <= 2e-3 * scale
    plain = np.maximum(lattice.sample(points, normalized=True) @ env, 0)
    assert np.abs(want - plain).max(axis=1)[sure].mean() > 0.05


def test_a_lattice_without_facings_draws_the_plain_lookup(renderer):
    """Facing unknown everywhere (an old file): FACING 0, the hardware trilinear lookup
    as before; a preview's facing is shown where the preview is."""
    lattice = _random_lattice()
    lattice.facing[:] = 0
    radiance, points, _ = _plane_frames(renderer, lattice, 50.0, shading="irradiance")
    assert not renderer.lattice.facing_known
    assert dict(renderer.lattice.facing_defines())["FACING"] == 0
    plain = lattice.sample(points, normalized=True)
    coords = lattice.geometry.to_texel_coords(points)
    weight = trilinear((lattice.samples > 0)[..., None].astype(np.float64), coords)[:, 0]
    baked = weight > 0.27  # below 0.25 local shading shows through
    assert baked.mean() > 0.8
    error = np.abs(radiance - plain).max(axis=1)
    assert (error <= _filtered_atol(weight))[baked].all()  # hardware filtering's rounding
    lattice.preview = np.zeros_like(lattice.values)
    lattice.preview_paths = np.zeros(lattice.samples.shape, np.uint16)
    lattice.preview_paths[2, 3, 4] = 5
    lattice.ensure_preview_facing()[2, 3, 4] = (200, 100)
    assert tuple(lattice.displayed_facing()[2, 3, 4]) == (200, 100)
    assert lattice.facing_known()


@pytest.mark.parametrize("with_facing", [True, False])
def test_a_sparse_lattice_is_read_through_its_bricks(renderer, with_facing):
    """A 24³ lattice (3 bricks a side) whose texels are shown in one region only: just the
    bricks a lookup can read them from get atlas slots, and the picture is
    `Lattice.sample`'s — the side-aware lookup (texel fetches) or, without facings, GL's
    trilinear filtering — across brick boundaries and where whole bricks have no slot."""
    geometry = LatticeGeometry((24, 24, 24), (-1.0,) * 3, (1.0,) * 3)
    rng = np.random.default_rng(5)
    values = rng.uniform(0.1, 1.0, (*geometry.shape, 3)).astype(np.float32)
    _, y, x = np.indices(geometry.shape)
    samples = ((x < 14) & (y >= 5) & (rng.random(geometry.shape) > 1 / 6)).astype(np.uint32)
    facing = (octahedral.encode(rng.normal(size=(*geometry.shape, 3))) if with_facing
              else None)
    lattice = Lattice(geometry, values, samples, np.zeros(geometry.shape, np.float32),
                      np.ones(geometry.shape, bool), {"kind": "irradiance"}, facing=facing)
    radiance, points, normals = _plane_frames(renderer, lattice, 50.0, shading="irradiance")
    textures = renderer.lattice
    assert textures.used - 1 == 2 * 3 * 3  # x: bricks 0, 1 of 3; every y and z brick
    want = lattice.sample(points, normalized=True, normals=normals if with_facing else None)
    sure = _sure(lattice, points, normals)
    coords = geometry.to_texel_coords(points)
    assert 0.2 < sure.mean() < 0.8 and (coords[:, 2] > 16).mean() > 0.1  # a brick unseen
    weight = trilinear((samples > 0)[..., None].astype(np.float64), coords)[:, 0]
    tolerance = 2.0**-9 + 1e-5 if with_facing else _filtered_atol(weight)
    error = np.abs(radiance - want).max(axis=1)
    assert (error <= tolerance)[sure].all(), error[sure].max()
