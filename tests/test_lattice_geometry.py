"""Where a lattice's texels are: `scale` texels per voxel along a volume's finest axis,
cubes where the voxels are not (at most `MAX_REFINEMENT` times as many per voxel along a
coarse axis), and a bake adds paths only to a file of the texels it places."""

import numpy as np
import pytest

from isolume.baking import BakeConfig, BakeError, bake
from isolume.baking import lattice as lattice_module
from isolume.baking.lattice import MAX_REFINEMENT, LatticeGeometry, other_texels, refinement
from isolume.volumes import Volume


def _box(shape_zyx, spacing_xyz, name="box") -> Volume:
    """A volume of `shape_zyx` voxels of `spacing_xyz`, a ball of value 1 in its middle."""
    axes = [(np.arange(n) - (n - 1) / 2) * s for n, s in zip(shape_zyx, spacing_xyz[::-1],
                                                               strict=True)]
    z, y, x = np.meshgrid(*axes, indexing="ij")
    radius = 0.3 * min(n * s for n, s in zip(shape_zyx, spacing_xyz[::-1], strict=True))
    data = 0.5 - 0.5 * np.tanh((np.sqrt(x * x + y * y + z * z) - radius) / min(spacing_xyz))
    origin = tuple(float(axes[2 - a][0]) for a in range(3))
    return Volume(data.astype(np.float32), spacing_xyz, origin, name=name, source=name)


@pytest.mark.parametrize(("shape", "spacing", "scale", "texels"), [
    ((10, 20, 20), (1.0, 1.0, 2.0), 1.0, (20, 20, 20)),  # slices twice as thick: cubes
    ((10, 20, 20), (1.0, 1.0, 2.0), 0.5, (10, 10, 10)),
    ((10, 20, 20), (1.0, 1.0, 1.4), 1.0, (14, 20, 20)),
    ((8, 30, 30), (1.0, 1.0, 5.0), 1.0, (16, 30, 30)),  # refined at most MAX_REFINEMENT
    ((31, 20, 20), (3.2, 3.2, 1.5), 1.0, (31, 40, 40)),  # the fine axis is z
    ((9, 11, 13), (0.9, 0.9, 0.9), 1.0, (9, 11, 13)),  # cubic voxels: one texel each
    ((9, 11, 13), (0.9, 0.9, 0.9), 0.5, (4, 6, 6)),  # round(n * scale), as ever
])
def test_texels_are_cubes_where_the_voxels_are_not(shape, spacing, scale, texels):
    vol = _box(shape, spacing)
    geometry = LatticeGeometry.for_volume(vol, scale)
    assert geometry.shape == texels
    assert all(isinstance(n, int) for n in geometry.shape)
    np.testing.assert_allclose(geometry.lo, vol.box[0])
    np.testing.assert_allclose(geometry.hi, vol.box[1])
    np.testing.assert_allclose(geometry.shape, np.multiply(shape, refinement(spacing)[::-1])
                               * scale, atol=0.5)  # rounded, no more
    if scale == 1 and max(spacing) / min(spacing) <= MAX_REFINEMENT:
        np.testing.assert_allclose(geometry.texel_size, min(spacing), rtol=0.05)  # cubes


def test_refinement_is_the_voxel_size_over_the_finest_within_its_cap():
    np.testing.assert_array_equal(refinement((1.0, 1.0, 1.0)), [1.0, 1.0, 1.0])
    np.testing.assert_allclose(refinement((0.5, 0.5, 0.8)), [1.0, 1.0, 1.6])
    np.testing.assert_array_equal(refinement((1.0, 3.0, 9.0)), [1.0, 2.0, 2.0])


def test_a_bake_adds_paths_only_to_a_file_of_the_texels_it_places(tmp_path, monkeypatch):
    """A file whose texels are as tall as the slices (another placement) is refused for a
    resumed bake in one line naming both shapes; the viewer shows it as it is with the
    same line (`other_texels`)."""
    vol = _box((10, 20, 20), (1.0, 1.0, 2.0), name="slices")
    config = BakeConfig(samples=2, bounces=0, env="constant:1,1,1")
    path = tmp_path / "tall.npz"
    monkeypatch.setattr(lattice_module, "MAX_REFINEMENT", 1.0)
    tall = bake(vol, config, out=path, workers=2)
    assert tall.geometry.shape == (10, 20, 20)
    monkeypatch.undo()
    message = other_texels(tall.geometry, vol, config.scale, path)
    assert message.startswith(f"{path}: a lattice of 10×20×20 texels") and "20×20×20" in message
    assert "\n" not in message
    with pytest.raises(BakeError, match=r"tall\.npz: a lattice of 10×20×20 texels.*20×20×20"):
        bake(vol, BakeConfig(samples=4, bounces=0, env="constant:1,1,1"), out=path, workers=2)
    fresh = bake(vol, config, out=tmp_path / "cubes.npz", workers=2)
    assert fresh.geometry.shape == (20, 20, 20)
    assert other_texels(fresh.geometry, vol, config.scale) == ""


def test_the_charts_cache_rebakes_a_lattice_of_other_texels(tmp_path, monkeypatch):
    """`isolume chart`'s lattice cache keys on the bake settings: a lattice cached with
    texels as tall as the slices is not taken for one of cubic texels."""
    from isolume.app.charts.lattices import LatticeStore

    vol = _box((10, 20, 20), (1.0, 1.0, 2.0), name="slices")
    config = BakeConfig(samples=2, bounces=0, env="constant:1,1,1")
    monkeypatch.setattr(lattice_module, "MAX_REFINEMENT", 1.0)
    tall = LatticeStore(vol, tmp_path, workers=2).get(config)
    monkeypatch.undo()
    again = LatticeStore(vol, tmp_path, workers=2).get(config)
    assert tall.lattice.geometry.shape == (10, 20, 20) and not tall.cached
    assert again.lattice.geometry.shape == (20, 20, 20) and not again.cached
    assert LatticeStore(vol, tmp_path, workers=2).get(config).cached


def test_the_viewer_shows_a_file_of_other_texels_as_it_is(tmp_path, monkeypatch):
    """An unfinished lattice file of texels as tall as the slices: the viewer shows it with
    `other_texels`' line on its status bar and starts no lazy bake into it."""
    from types import SimpleNamespace

    from isolume.app.viewer import illumination
    from isolume.baking.view_texels import LatticeOnFile

    vol = _box((10, 20, 20), (1.0, 1.0, 2.0), name="slices")
    path = tmp_path / "tall.npz"
    monkeypatch.setattr(lattice_module, "MAX_REFINEMENT", 1.0)
    bake(vol, BakeConfig(samples=2, bounces=0, env="constant:1,1,1"), out=path, workers=2)
    monkeypatch.undo()
    monkeypatch.setattr(illumination, "_complete", lambda lattice, samples: False)
    started, shown = [], []
    monkeypatch.setattr(illumination.Illumination, "_start_bake",
                        lambda self, *args: started.append(args))
    drawing = SimpleNamespace(albedo=None, show_lattice=lambda lattice: shown.append(lattice))
    state = SimpleNamespace(message="")
    light = illumination.Illumination(vol, drawing, state, SimpleNamespace(bake=True))
    light.start(LatticeOnFile.open(path, vol), 0.5)
    assert not started and len(shown) == 1 and light.static_lattice is shown[0]
    assert state.message.startswith(f"{path}: a lattice of 10×20×20 texels")


@pytest.mark.parametrize("threads", [1, 3])
def test_many_points_convert_in_blocks_to_the_same_bits(threads):
    """`to_texel_coords` of more points than `COORD_BLOCK` (in blocks on the pool) and
    `preview._eye_directions` (in `EYE_BLOCK`s) give, on 1 and 3 threads, the bits of the
    same arithmetic on all the points at once — NaN and the eye itself included."""
    from isolume.baking import preview
    from isolume.volumes import cores

    geometry = LatticeGeometry.for_volume(_box((10, 20, 20), (1.0, 1.0, 2.0)), 1.0)
    lo, size = np.array(geometry.lo), geometry.texel_size
    rng = np.random.default_rng(4)
    eye = np.array([3.0, -40.0, 7.5])
    cores.use(threads)
    try:
        for count in (lattice_module.COORD_BLOCK, lattice_module.COORD_BLOCK + 1,
                      3 * lattice_module.COORD_BLOCK + 17):
            points = rng.uniform(-12, 12, (count, 3)).astype(np.float32)
            points[[0, count // 2]] = np.nan
            points[-1] = eye
            got = geometry.to_texel_coords(points)
            want = ((points.astype(np.float64) - lo) / size - 0.5)[:, ::-1]
            np.testing.assert_array_equal(got, want)
            towards = points.astype(np.float64) - eye
            length = np.linalg.norm(towards, axis=1)
            dirs, usable = preview._eye_directions(points, eye)
            np.testing.assert_array_equal(usable, np.isfinite(length) & (length > 0))
            with np.errstate(divide="ignore", invalid="ignore"):
                np.testing.assert_array_equal(dirs, towards / length[:, None])
    finally:
        cores.use(None)
