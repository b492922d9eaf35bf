"""Volume conventions (DESIGN §2), validation, synthetic volumes and suggested isovalues."""

import warnings

import numpy as np
import pytest
from scipy import ndimage

from isolume import volumes
from isolume.volumes import Volume, VolumeError
from isolume.volumes.synthetic import NAMES, make


def test_world_position_of_voxel_follows_convention():
    data = np.zeros((3, 4, 5), np.float32)  # z, y, x
    vol = Volume(data, spacing=(0.5, 2.0, 3.0), origin=(1.0, -1.0, 10.0))
    world = vol.index_to_world(np.array([[2, 3, 4]]))  # (k, j, i)
    np.testing.assert_allclose(world, [[1.0 + 4 * 0.5, -1.0 + 3 * 2.0, 10.0 + 2 * 3.0]])
    np.testing.assert_allclose(vol.world_to_index(world), [[2, 3, 4]])
    assert vol.shape_xyz == (5, 4, 3)
    lo, hi = vol.box
    np.testing.assert_allclose(lo, [0.75, -2.0, 8.5])
    np.testing.assert_allclose(hi, lo + np.array([5 * 0.5, 4 * 2.0, 3 * 3.0]))


def test_value_at_is_trilinear_and_exact_at_voxels():
    rng = np.random.default_rng(3)
    vol = Volume(rng.random((4, 5, 6)).astype(np.float32), spacing=(1, 2, 3), origin=(1, 2, 3))
    idx = np.array([[1, 2, 3], [3, 4, 5]])
    np.testing.assert_allclose(volumes.value_at(vol, vol.index_to_world(idx)),
                               vol.data[idx[:, 0], idx[:, 1], idx[:, 2]], rtol=1e-6)
    mid = vol.index_to_world(np.array([[1.5, 2, 3]]))
    expected = 0.5 * (vol.data[1, 2, 3] + vol.data[2, 2, 3])
    np.testing.assert_allclose(volumes.value_at(vol, mid), [expected], rtol=1e-6)


def test_smoothed_gradient_of_linear_field_is_exact():
    """The cubic B-spline reproduces linear functions, so its gradient is exact there."""
    z, y, x = np.meshgrid(np.arange(6), np.arange(7), np.arange(8), indexing="ij")
    data = (2.0 * x + 3.0 * y - 1.0 * z).astype(np.float32)
    vol = Volume(data, spacing=(0.5, 1.0, 2.0))
    points = vol.index_to_world(np.array([[2.5, 3.25, 4.75]]))  # interior
    for smooth in (True, False):
        g = volumes.gradient_at(vol, points, smooth=smooth)
        np.testing.assert_allclose(g, [[2.0 / 0.5, 3.0 / 1.0, -1.0 / 2.0]], rtol=1e-5)
    n = volumes.normals_at(vol, points)
    expected = -np.array([4.0, 3.0, -0.5]) / np.linalg.norm([4.0, 3.0, -0.5])
    np.testing.assert_allclose(n[0], expected, rtol=1e-5)
    np.testing.assert_allclose(volumes.normals_at(vol, points, flip=True)[0], -expected, rtol=1e-5)


@pytest.mark.parametrize(
    ("data", "kwargs", "match"),
    [
        (np.zeros((1, 4, 4)), {}, "smaller than 2×2×2"),
        (np.zeros((4, 4)), {}, "3-D array"),
        (np.array([[[np.nan, 0], [0, 0]], [[0, 0], [0, 0]]]), {}, "NaN/Inf"),
        (np.zeros((2, 2, 2)), {"spacing": (1, 0, 1)}, "spacing must be positive"),
        (np.zeros((2, 2, 2)), {"spacing": (1, 1)}, "three"),
        (np.full((2, 2, 2), "a"), {}, "real numbers"),
    ],
)
def test_bad_volumes_are_refused_with_one_line(data, kwargs, match):
    with pytest.raises(VolumeError, match=match) as info:
        Volume(data, source="bad.npy", **kwargs)
    assert "\n" not in str(info.value) and "bad.npy" in str(info.value)


@pytest.mark.parametrize("name", NAMES)
def test_synthetic_volumes_have_surfaces_at_their_isovalues(name):
    vol = make(name, 48)
    assert vol.data.dtype == np.float32 and vol.data.shape[2] == 48
    assert vol.suggested_iso, "synthetic volumes know their isovalues"
    for iso in vol.suggested_iso:
        mesh = volumes.isosurface(vol, iso)
        assert not mesh.empty, f"{name} at {iso}"
        lo, hi = vol.sample_box
        assert (mesh.vertices >= lo - 1e-5).all() and (mesh.vertices <= hi + 1e-5).all()


def test_synthetic_volumes_are_deterministic():
    a, b = make("mixing_layer", 24), make("mixing_layer", 24)
    np.testing.assert_array_equal(a.data, b.data)
    assert a.data_hash() == b.data_hash()


@pytest.mark.parametrize("spec", ["synthetic:nope", "synthetic:sphere:abc", "synthetic:sphere:4"])
def test_bad_synthetic_specs(spec):
    with pytest.raises(VolumeError, match=spec.split(":")[1] if "nope" in spec else "size|SIZE"):
        volumes.load(spec)


def test_suggested_isovalues_separate_three_materials():
    """Multi-Otsu on air | tissue | bone-like data puts thresholds between the plateaus."""
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 3, size=(20, 20, 20))
    data = np.choose(labels, [0.0, 100.0, 1000.0]) + rng.normal(0, 5, labels.shape)
    suggested = volumes.suggest_isovalues(Volume(data.astype(np.float32)))
    assert len(suggested) == 2
    assert 5 < suggested[0] < 95 and 105 < suggested[1] < 995


@pytest.mark.parametrize("case", ["three plateaus", "skewed", "three values", "ties"])
def test_multi_otsu_is_scikit_images(case):
    """The thresholds `suggest_isovalues` computes without scikit-image's thresholding
    module are that module's own, bit for bit (29 scans of the data folder checked too),
    and too few distinct values is a ValueError as there."""
    from skimage.filters import threshold_multiotsu

    from isolume.volumes.stats import multi_otsu

    rng = np.random.default_rng(7)
    values = {
        "three plateaus": np.choose(rng.integers(0, 3, 50_000), [0.0, 80.0, 900.0])
        + rng.normal(0, 9, 50_000),
        "skewed": rng.gamma(1.5, 40.0, 80_000),
        "three values": np.choose(rng.integers(0, 3, 5_000), [2.0, 5.0, 11.0]),
        "ties": np.repeat(np.arange(12.0), 100),
    }[case].astype(np.float32)
    expected = threshold_multiotsu(values, classes=3, nbins=256)
    got = multi_otsu(values, 3)
    assert got.dtype == expected.dtype and np.array_equal(got, expected)
    two = np.repeat(np.float32([1.0, 4.0]), 10)
    with pytest.raises(ValueError):
        threshold_multiotsu(two, classes=3, nbins=256)
    with pytest.raises(ValueError, match="2 bins hold values, 3 classes"):
        multi_otsu(two, 3)


def test_constant_volume_has_no_suggestion_and_an_empty_surface():
    vol = Volume(np.full((4, 4, 4), 7.0), source="flat.npy")
    assert volumes.suggest_isovalues(vol) == ()
    mesh = volumes.isosurface(vol, 7.0)
    assert mesh.empty and "extreme" in mesh.message


def _two_values(dtype, low, high) -> np.ndarray:
    """(4, 4, 4) samples of type `dtype`: `low` in one half, `high` in the other."""
    data = np.full((4, 4, 4), low, dtype)
    data[2:] = high
    return data


@pytest.mark.parametrize(("data", "constant"), [
    (np.full((4, 4, 4), 7, np.uint8), True),
    (np.full((4, 4, 4), 3.5, np.float32), True),
    (np.full((4, 4, 4), 3e38, np.float32), True),
    (np.float32(1e8) + np.arange(64, dtype=np.float32).reshape(4, 4, 4) * 100 / 63, False),
    (_two_values(np.int32, 2**31 - 2, 2**31 - 1), True),  # both become 2^31 in float32
])
def test_info_of_constant_and_narrow_volumes(data, constant, capsys):
    """The histogram's edges are float64, increasing however narrow the range beside the
    values' magnitude; a constant volume reaches "none (constant volume)"."""
    from isolume.volumes.stats import VolumeInfo

    info = VolumeInfo.of(Volume(data, source="v.raw"))
    assert (np.diff(info.edges) > 0).all() and info.counts.sum() == data.size
    labels = [line.split("..") for line in info.histogram_lines]
    assert len({float(lo) for lo, _ in labels}) == len(labels)  # edges told apart
    assert ("none (constant volume)" in str(info)) == constant
    capsys.readouterr()


@pytest.mark.parametrize("spacing", [(1e300, 1, 1), (1, 1e-300, 1), (1e-30, 1e-30, 1e-30),
                                     (1, 1, 2e12)])
def test_spacing_beyond_float32_world_coordinates_is_refused(spacing):
    with pytest.raises(VolumeError, match=r"v\.raw: spacing .* rescale the units with --spacing"):
        Volume(np.zeros((4, 4, 4), np.float32), spacing=spacing, source="v.raw")


@pytest.mark.parametrize(("origin", "spacing"), [
    ((1e300, 0, 0), 1.0),
    ((5e5, 4e6, 0), 1.0),
    ((5e5, 4e6, 0), 0.01),
    ((0, 0, -30000), 1.0),
])
def test_volume_far_from_the_world_origin_is_refused(origin, spacing):
    """Beyond 1024 extents from the world origin float32 coordinates lose much of a
    voxel: the error says how far the volume lies and what to do."""
    with pytest.raises(VolumeError, match=r"v\.raw: the volume lies .* from the world origin"
                       r".*times its largest extent .*--origin 0,0,0 \(origin= in Python\)"):
        Volume(np.zeros((24, 24, 24), np.float32), spacing=(spacing,) * 3, origin=origin,
               source="v.raw")


def test_volume_near_the_world_origin_is_kept():
    vol = Volume(np.zeros((24, 24, 24), np.float32), origin=(1e4, 1e4, -1e4))
    assert vol.origin == (1e4, 1e4, -1e4)
    Volume(np.zeros((2, 2, 2), np.float32), spacing=(1e-12, 1e-12, 1e-12))
    Volume(np.zeros((2, 2, 2), np.float32), spacing=(1e12, 1e12, 1e12))


@pytest.mark.parametrize(("data", "said"), [
    (_two_values(np.int32, 16777216, 16777217), "16777217 became 16777216"),
    (_two_values(np.int32, 2**31 - 2, 2**31 - 1), "2147483646 became 2147483648"),
    (_two_values(np.uint64, 2**63, 2**63 + 63), "9223372036854775871 became "
     "9223372036854775808"),
    (_two_values(np.float64, 1e8, 1e8 + 100), "100000100.0 became 100000096.0"),
])
def test_inexact_conversion_to_float32_warns_once(data, said, capsys):
    vol = Volume(data, source="v.raw")
    assert vol.data.dtype == np.float32
    err = capsys.readouterr().err
    assert err.startswith("isolume: warning: v.raw: ") and err.count("\n") == 1
    assert str(data.dtype) in err and said in err and "rounded" in err


@pytest.mark.parametrize("data", [
    np.arange(64, dtype=np.int32).reshape(4, 4, 4) * 262144 - 2**24,  # within ±2^24
    np.arange(64, dtype=np.int64).reshape(4, 4, 4) << 40,  # large, and floats
    np.arange(64, dtype=np.uint32).reshape(4, 4, 4),
    np.random.default_rng(2).random((4, 4, 4)),  # float64: rounding ~3e-8 of the range
    np.arange(64, dtype=np.float16).reshape(4, 4, 4),
])
def test_exact_conversion_to_float32_is_silent(data, capsys):
    vol = Volume(data, source="v.raw")
    assert vol.data.dtype == np.float32 and capsys.readouterr().err == ""
    np.testing.assert_allclose(vol.data, data, rtol=2**-24)


def test_float64_beyond_float32_is_refused_as_such():
    data = _two_values(np.float64, -1e300, 1e300)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning from the cast
        with pytest.raises(VolumeError, match=r"v\.raw: value -1e\+300 \(float64\) is beyond "
                           r"float32's range"):
            Volume(data, source="v.raw")


def _map_coordinates(grid, index_zyx):
    from scipy import ndimage

    if grid.ndim == 3:
        return ndimage.map_coordinates(grid, index_zyx.T, order=1, mode="nearest")
    return np.stack([_map_coordinates(grid[..., c], index_zyx) for c in range(grid.shape[-1])],
                    axis=-1)


def test_compiled_trilinear_equals_scipy_map_coordinates():
    """The compiled lookup against scipy's order-1 interpolation with edge clamping,
    inside, outside and on the faces of the grid, scalar and vector grids alike."""
    from isolume.volumes.field import _interpolate

    r = np.random.default_rng(4)
    for shape in [(5, 6, 7), (5, 6, 7, 3), (1, 4, 3)]:
        grid = r.normal(size=shape).astype(np.float32)
        idx = r.uniform(-2, 9, size=(5000, 3))
        idx[:10] = np.floor(idx[:10])  # exactly on samples
        np.testing.assert_array_equal(_interpolate(grid, idx), _map_coordinates(grid, idx))


def test_world_lookups_equal_scipy_map_coordinates():
    """The compiled lookups at world points — `value_in` (the Newton steps' and their line
    search's, handed the grid's placement as six floats) and `value_at_world` (handed the
    arrays, rounded to its scratch's type) — against scipy's order-1 interpolation at the
    indices (p − origin) / spacing, on an anisotropic, shifted grid: inside, outside and
    on its faces."""
    from isolume.volumes.field import frame_of, value_at_world, value_in

    r = np.random.default_rng(9)
    grid = r.normal(size=(5, 6, 7)).astype(np.float32)
    origin, spacing = np.array([-1.5, 2.0, 0.25]), np.array([0.5, 1.25, 2.0])  # x, y, z
    world = origin + r.uniform(-2, 9, size=(2000, 3)) * spacing
    world[:10] = origin + np.floor(r.uniform(0, 5, size=(10, 3))) * spacing  # on samples
    expected = _map_coordinates(grid, ((world - origin) / spacing)[:, ::-1])
    data, frame = grid[..., None], frame_of(origin, spacing)
    scratch = np.empty(1, np.float32)
    got = np.array([value_in(data, frame, *p) for p in world])
    np.testing.assert_array_equal(got.astype(np.float32), expected)
    rounded = np.array([value_at_world(data, origin, spacing, *p, scratch) for p in world])
    np.testing.assert_array_equal(rounded, got.astype(np.float32))


def _gradient_grid(vol) -> np.ndarray:
    """(Z, Y, X, 3) float32 smoothed gradient at the voxels, with scipy: the central
    difference along one axis, the B-spline weights [1, 4, 1] / 6 along the other two."""
    spline, central = np.array([1.0, 4.0, 1.0]) / 6.0, np.array([-0.5, 0.0, 0.5])
    data = vol.data.astype(np.float64)
    out = []
    for axis, h in zip((2, 1, 0), vol.spacing, strict=True):  # x, y, z
        g = data
        for a in range(3):
            g = ndimage.correlate1d(g, central if a == axis else spline, axis=a,
                                    mode="nearest")
        out.append(g / h)
    return np.stack(out, axis=-1).astype(np.float32)


@pytest.mark.parametrize("smooth", [True, False])
def test_gradients_are_the_voxel_stencils_interpolated(smooth):
    """`gradient_at` (the voxels' gradients computed where a lookup needs them) against
    scipy's filters over the whole grid, interpolated by scipy, inside, outside and on the
    faces; plain differences without the B-spline weights."""
    vol = make("torus", 24)
    grid = _gradient_grid(vol) if smooth else np.stack(
        [np.gradient(vol.data.astype(np.float64), h, axis=a, edge_order=1)
         for a, h in zip((2, 1, 0), vol.spacing, strict=True)], axis=-1).astype(np.float32)
    if not smooth:  # np.gradient's one-sided edges: compare inside only
        grid = grid[1:-1, 1:-1, 1:-1]
    r = np.random.default_rng(8)
    last = np.array(vol.data.shape) - 1
    index = (r.uniform(-2, last + 2, size=(4000, 3)) if smooth  # outside too: clamped
             else r.uniform(1, last - 1, size=(4000, 3)))
    index[:10] = np.floor(index[:10])
    points = vol.index_to_world(index)
    expected = _map_coordinates(grid, index if smooth else index - 1)
    got = volumes.gradient_at(vol, points, smooth=smooth)
    scale = np.abs(grid).max()
    np.testing.assert_allclose(got, expected, atol=1e-6 * scale)
    assert np.isnan(volumes.gradient_at(vol, np.full((1, 3), np.nan))).all()


def test_newton_projection_matches_the_plain_iteration():
    """`newton_to_level` against the same damped Newton steps written with scipy lookups:
    each step at most one voxel long, four steps plus one per voxel of `max_move` (it stops
    once a step moves less than 1e-4 voxel: the points agree to 2e-4 voxel)."""
    vol = make("torus", 40)
    grad = _gradient_grid(vol)
    r = np.random.default_rng(3)
    start = vol.index_to_world(r.uniform(2, 37, size=(3000, 3)))
    levels = r.uniform(0.2, 0.8, 3000)
    max_move = 2.0 * min(vol.spacing)
    p = start.copy()
    voxel = min(vol.spacing)
    for _ in range(4 + int(max_move / voxel)):
        idx = vol.world_to_index(p)
        rho = _map_coordinates(vol.data, idx)
        g = _map_coordinates(grad, idx).astype(np.float64)
        g2 = np.maximum((g * g).sum(axis=1), 1e-30)
        step = (levels - rho) / g2
        step *= np.minimum(1.0, voxel / np.maximum(np.abs(step) * np.sqrt(g2), 1e-30))
        p = p + step[:, None] * g
        d = p - start
        dist = np.linalg.norm(d, axis=1, keepdims=True)
        p = start + d * np.minimum(1.0, max_move / np.maximum(dist, 1e-30))
    got = volumes.newton_to_level(vol, start, levels, max_move)
    np.testing.assert_allclose(got, p, atol=2e-4 * min(vol.spacing))


def test_newton_projection_is_the_same_whatever_the_threads(monkeypatch):
    """Cut into items on threads (`cores.MIN_COST`), every point lands bit for bit where
    one call puts it."""
    from isolume.volumes import cores

    vol = make("torus", 40)
    r = np.random.default_rng(5)
    start = vol.index_to_world(r.uniform(2, 37, size=(3001, 3)))
    levels = r.uniform(0.2, 0.8, 3001)
    whole = volumes.newton_to_level(vol, start, levels, 2.0 * min(vol.spacing))
    monkeypatch.setattr(cores, "MIN_COST", 100)
    cores.use(7)
    try:
        moved = volumes.newton_to_level(vol, start, levels, 2.0 * min(vol.spacing))
    finally:
        cores.use(None)
    assert len(cores.item_bounds(len(start), 1)) > 7
    np.testing.assert_array_equal(moved, whole)


@pytest.mark.parametrize("flip", [False, True])
def test_values_along_normals_equal_lookups_at_the_moved_points(flip):
    """The compiled pass against `normals_at` and `value_at` (float32 normals there, hence
    the tolerance: a value gradient of ~1 per voxel times 1e-7 of a voxel)."""
    vol = make("torus", 40)
    r = np.random.default_rng(7)
    points = vol.index_to_world(r.uniform(2, 37, size=(5000, 3)))
    distance = 0.3 * min(vol.spacing)
    moved = points + distance * volumes.normals_at(vol, points, flip=flip).astype(np.float64)
    np.testing.assert_allclose(volumes.values_along_normals(vol, points, distance, flip=flip),
                               volumes.value_at(vol, moved), rtol=0, atol=1e-5)


@pytest.mark.parametrize("dtype", ["uint8", "int16", "uint16"])
def test_integer_samples_stay_as_stored_and_answer_as_float32(dtype):
    """A volume of 8- or 16-bit samples keeps them (a quarter or half of float32's
    memory), and every reader answers to the bit as for the same samples as float32: the
    identity hash, the suggested isovalues, the meshes, gradients and values, the level
    crossings and the tracing surface (integer differences must not wrap)."""
    from isolume.volumes import field
    from isolume.volumes.cubes import tracing_surface

    rng = np.random.default_rng(4)
    sphere = make("sphere", 24).data
    low = -200 if dtype == "int16" else 0
    data = (low + sphere * 230 + rng.integers(0, 25, sphere.shape)).astype(dtype)
    stored, floats = Volume(data), Volume(data.astype(np.float32))
    assert stored.data.dtype == np.dtype(dtype) and stored.data.nbytes < floats.data.nbytes
    assert stored.data_hash() == floats.data_hash()
    isos = volumes.suggest_isovalues(stored)
    assert isos == volumes.suggest_isovalues(floats) and len(isos) == 2
    a, b = volumes.isosurface(stored, isos[0]), volumes.isosurface(floats, isos[0])
    for name in ("vertices", "faces", "normals"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    points = a.vertices[::5].astype(np.float64) + 0.3
    for smooth in (True, False):
        np.testing.assert_array_equal(field.gradient_at(stored, points, smooth),
                                      field.gradient_at(floats, points, smooth))
    np.testing.assert_array_equal(volumes.value_at(stored, points),
                                  volumes.value_at(floats, points))
    np.testing.assert_array_equal(volumes.level_points(stored, isos[0]),
                                  volumes.level_points(floats, isos[0]))
    for x, y in zip(tracing_surface(stored, isos[1]), tracing_surface(floats, isos[1]),
                    strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("dtype", [np.float32, np.uint8, np.int16])
def test_compiled_normals_are_the_arrays_normals_to_the_bit(dtype):
    """`normals_at` (one compiled pass, `field.normal_in`) against
    `normals_from_gradient(gradient_at(...))`, the array code it stands for: the same
    float32 bits everywhere — inside and outside the box, in a flat region (0, 0, 1), at
    NaN points, where the squared gradient overflows float32 — smoothed or not, flipped
    or not, on a volume with its own origin and spacing."""
    from isolume.volumes.field import gradient_at, normals_from_gradient

    rng = np.random.default_rng(1)
    data = make("engine", 40).data.astype(np.float32)
    data[2:8, 5:12, 5:12] = 0.25  # flat
    scale = {np.float32: 1.0, np.uint8: 255.0, np.int16: 3000.0}[dtype]
    data = (data * scale).astype(dtype)
    if dtype == np.float32:
        data[15, 20, 20], data[16, 20, 20] = 3e38, -3e38  # |g|² past float32's range
    vol = Volume(data, spacing=(0.7, 1.0, 1.3), origin=(1.0, -2.0, 0.5))
    lo, hi = vol.box
    points = rng.uniform(np.array(lo) - 2, np.array(hi) + 2, (50_000, 3))
    points[:10] = np.nan
    points[10:20, 1] = np.nan
    points[20:1000] = np.array(vol.origin) + np.array(vol.spacing) * (
        np.array([8.5, 8.0, 4.5]) + rng.uniform(-1, 1, (980, 3)))  # in the flat block
    for smooth in (True, False):
        for flip in (False, True):
            with np.errstate(over="ignore"):
                want = normals_from_gradient(gradient_at(vol, points, smooth), flip)[0]
            got = volumes.normals_at(vol, points, smooth, flip)
            np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
            assert (np.abs(want) == [0, 0, 1]).all(axis=1).sum() > 100
            assert np.isnan(want).any(axis=1).sum() == 20
