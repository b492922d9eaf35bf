"""Parts of volumes: ``--crop`` voxel ranges and ``--downsample`` block means keep the
world place (a surface stays where it was), read only the part from files that can be
mapped (memory measured with tracemalloc), and refuse bad ranges in one line naming the
volume's dims."""

from __future__ import annotations

import re
import tracemalloc

import numpy as np
import pytest
from scipy.spatial import cKDTree

from isolume import volumes
from isolume.app.cli import main
from isolume.volumes.core import VolumeError
from isolume.volumes.io import load_file
from isolume.volumes.region import Region, parse_crop, read_region, resolve_region

SPACING = (0.5, 0.75, 1.25)
ORIGIN = (-3.0, 2.0, 10.0)


def _random_volume(shape_zyx=(13, 17, 19), seed=0) -> volumes.Volume:
    data = np.random.default_rng(seed).random(shape_zyx, dtype=np.float32)
    return volumes.Volume(data, spacing=SPACING, origin=ORIGIN, name="r")


def _block_means_by_loops(data: np.ndarray, f: int) -> np.ndarray:
    """Reference: mean of each whole f³ block, by explicit loops (partial blocks left out)."""
    nz, ny, nx = (n // f for n in data.shape)
    out = np.empty((nz, ny, nx))
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                out[k, j, i] = data[k * f:(k + 1) * f, j * f:(j + 1) * f,
                                    i * f:(i + 1) * f].astype(np.float64).mean()
    return out


def _distance_ball(n=48, spacing=0.5) -> volumes.Volume:
    """Distance from the world point (1.3, -0.7, 0.4), sampled on n³ voxels."""
    origin = np.array([-12.0, -11.0, -12.5])
    k, j, i = np.mgrid[0:n, 0:n, 0:n].astype(np.float64)
    x, y, z = (origin[a] + spacing * c for a, c in enumerate((i, j, k)))
    r = np.sqrt((x - 1.3) ** 2 + (y + 0.7) ** 2 + (z - 0.4) ** 2)
    return volumes.Volume(r.astype(np.float32), spacing=(spacing,) * 3, origin=tuple(origin))


# ---------------------------------------------------------------------------- syntax


@pytest.mark.parametrize(("text", "ranges"), [
    (":,:,:", ((None, None),) * 3),
    ("10:20, 5: ,:7", ((10, 20), (5, None), (None, 7))),
    ("0:2,0:2,0:2", ((0, 2),) * 3),
])
def test_crop_syntax(text, ranges):
    assert parse_crop(text).ranges == ranges


@pytest.mark.parametrize("text", ["", "1:2,3:4", "1:2,3:4,5:6,7:8", "a:b,:,:", "1.5:3,:,:",
                                  "-5:,:,:", "5,:,:", "1:2:3,:,:"])
def test_bad_crop_syntax_is_one_line(text):
    with pytest.raises(VolumeError, match=r"--crop .*expected X0:X1,Y0:Y1,Z0:Z1") as info:
        parse_crop(text)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(("crop", "factor", "fragment"), [
    ("0:20,:,:", 1, "x range 0:20 goes past the 19 voxels along x"),
    (":,17:,:", 1, "y range 17:17 goes past the 17 voxels along y"),
    (":,:,5:5", 1, "z range 5:5 is empty"),
    (":,:,9:4", 1, "z range 9:4 is empty"),
    ("3:4,:,:", 1, "x range 3:4 holds 1 voxel"),
    (":,:,0:7", 4, "--downsample 4 leaves 1 block(s) of the 7 voxels of z range 0:7"),
    (None, 7, "--downsample 7 leaves 1 block(s) of the 13 voxels along z"),
])
def test_bad_ranges_name_the_volume_dims(crop, factor, fragment):
    with pytest.raises(VolumeError) as info:
        resolve_region((19, 17, 13), crop, factor, "vol.raw")
    message = str(info.value)
    assert fragment in message and "(volume dims 19 x 17 x 13)" in message
    assert message.startswith("vol.raw: ") and "\n" not in message


@pytest.mark.parametrize("factor", [0, -2, 1.5, "2", True])
def test_bad_downsample_factor(factor):
    with pytest.raises(VolumeError, match=re.escape(f"--downsample {factor!r}: expected an "
                                                    "integer factor ≥ 1")):
        resolve_region((8, 8, 8), None, factor, "v")


# ----------------------------------------------------------------- semantics in memory


def test_crop_keeps_samples_and_moves_the_origin_to_its_first_voxel():
    vol = _random_volume()
    part = volumes.crop_downsample(vol, "4:15,:9,10:", 1)
    np.testing.assert_array_equal(part.data, vol.data[10:, :9, 4:15])
    assert part.spacing == vol.spacing
    np.testing.assert_allclose(part.origin, np.add(ORIGIN, np.multiply((4, 0, 10), SPACING)))
    # every kept voxel sits where it was in world space
    index = np.array([[0, 0, 0], [2, 8, 10]])  # (z, y, x) in the part
    np.testing.assert_allclose(part.index_to_world(index),
                               vol.index_to_world(index + np.array([10, 0, 4])))
    assert "cropped to voxels x 4:15, y 0:9, z 10:13 of 19 x 17 x 13" in part.placement


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_downsample_is_block_means_at_block_centres(factor):
    vol = _random_volume()
    part = volumes.crop_downsample(vol, None, factor)
    np.testing.assert_allclose(part.data, _block_means_by_loops(vol.data, factor), rtol=1e-6)
    np.testing.assert_allclose(part.spacing, np.multiply(SPACING, factor))
    # sample (0, 0, 0) of the part is the centre of the first block's corner voxels
    centre = vol.index_to_world(np.array([[0, 0, 0], [factor - 1] * 3])).mean(axis=0)
    np.testing.assert_allclose(part.origin, centre)
    left = [n % factor for n in vol.shape_xyz]
    if any(left):
        assert "left out: no whole block" in part.placement


def test_crop_then_downsample_counts_blocks_from_the_crop():
    vol = _random_volume()
    part = volumes.crop_downsample(vol, "3:,1:16,2:12", 2)
    np.testing.assert_allclose(part.data, _block_means_by_loops(vol.data[2:12, 1:16, 3:], 2),
                               rtol=1e-6)
    first = np.add(ORIGIN, (np.array([3, 1, 2]) + 0.5) * SPACING)
    np.testing.assert_allclose(part.origin, first)
    assert part.shape_xyz == (8, 7, 5)


def test_the_whole_volume_is_returned_as_it_is():
    vol = _random_volume()
    assert volumes.crop_downsample(vol, ":,:,:", 1) is vol
    assert volumes.crop_downsample(vol) is vol


def test_slabs_give_the_same_means_as_one_read(monkeypatch):
    from isolume.volumes import region as region_module

    data = np.random.default_rng(3).integers(0, 4000, (24, 10, 12)).astype(np.uint16)
    region = Region((12, 10, 24), (1, 0, 2), (12, 10, 23), 3)
    whole = read_region(data, region)
    monkeypatch.setattr(region_module, "SLAB_BYTES", 1)  # one output plane per slab
    np.testing.assert_array_equal(read_region(data, region), whole)
    np.testing.assert_allclose(whole, _block_means_by_loops(data[2:23, 0:9, 1:10], 3),
                               rtol=1e-6)


# ------------------------------------------------------------------- world space


def test_a_downsampled_ball_keeps_its_world_radius_and_centre():
    vol = _distance_ball()
    for factor in (2, 3, 4):
        part = volumes.crop_downsample(vol, None, factor)
        mesh = volumes.isosurface(part, 6.0, normals="none")
        r = np.linalg.norm(mesh.vertices - [1.3, -0.7, 0.4], axis=1)
        block = factor * vol.spacing[0]
        assert np.abs(r - 6.0).max() < block, (factor, np.abs(r - 6.0).max())
        # an origin left at the first voxel would move the centre by (N − 1)/2 voxels
        centre = mesh.vertices.mean(axis=0)
        np.testing.assert_allclose(centre, [1.3, -0.7, 0.4], atol=0.1 * block)


def test_a_cropped_surface_lies_on_the_whole_one():
    vol = _distance_ball()
    whole = volumes.isosurface(vol, 6.0, normals="none")
    part = volumes.crop_downsample(vol, "20:,5:40,:30", 1)
    cut = volumes.isosurface(part, 6.0, normals="none")
    assert len(cut.vertices) > 100
    distance, _ = cKDTree(whole.vertices).query(cut.vertices)
    assert distance.max() < 1e-4
    lo, hi = part.sample_box
    inside = np.all((whole.vertices > lo + 1e-6) & (whole.vertices < hi - 1e-6), axis=1)
    back, _ = cKDTree(cut.vertices).query(whole.vertices[inside])
    assert inside.sum() > 100 and back.max() < 1e-4


# ------------------------------------------------------------------- files, read in part


def _write_raw(tmp_path, data: np.ndarray, gz: bool = False):
    import gzip

    z, y, x = data.shape
    name = f"v_{x}x{y}x{z}_{data.dtype.name}.raw"
    path = tmp_path / (name + ".gz" if gz else name)
    payload = data.astype(data.dtype.newbyteorder("<")).tobytes()
    path.write_bytes(gzip.compress(payload) if gz else payload)
    return path


@pytest.mark.parametrize("crop", [None, "2:17,3:,:11"])
@pytest.mark.parametrize("factor", [1, 2, 3])
def test_raw_npy_and_gz_parts_match_the_part_of_the_whole(tmp_path, crop, factor):
    data = np.random.default_rng(5).integers(0, 60000, (13, 17, 19)).astype(np.uint16)
    whole = load_file(_write_raw(tmp_path, data), spacing=SPACING, origin=ORIGIN)
    want = volumes.crop_downsample(whole, crop, factor)
    np.save(tmp_path / "v.npy", data)
    paths = [_write_raw(tmp_path, data), _write_raw(tmp_path, data, gz=True),
             tmp_path / "v.npy"]
    for path in paths:
        got = load_file(path, spacing=SPACING, origin=ORIGIN, crop=crop, downsample=factor)
        np.testing.assert_array_equal(got.data, want.data, err_msg=str(path))
        assert got.spacing == want.spacing and got.origin == want.origin
        if crop or factor > 1:  # the same line on the part, after the format's own
            assert got.placement.endswith(want.placement.split("; ", 1)[1])


def test_an_oriented_nrrd_is_cropped_as_placed(tmp_path):
    """The crop counts in the placed volume's axes; the mapped file is read through the
    placement's flips and transposes."""
    nrrd = pytest.importorskip("nrrd")
    data = np.random.default_rng(6).integers(-900, 900, (9, 11, 14)).astype(np.int16)
    axes = np.array([[0.0, 0, -1], [-1, 0, 0], [0, 1, 0]])  # RAS columns: index x, y, z
    for name, header in {
        "attached.nrrd": {},
        "detached.nhdr": {"encoding": "raw"},
    }.items():
        path = tmp_path / name
        nrrd.write(str(path), data, {"space": "right-anterior-superior",
                                     "space directions": (axes * [0.5, 0.8, 1.5]).T,
                                     "space origin": np.array([4.0, -2.0, 7.0]),
                                     "encoding": "raw", **header},
                   index_order="C", detached_header=name.endswith(".nhdr"))
        whole = load_file(path)
        for crop, factor in ((":,:,:", 2), ("1:8,2:,3:10", 1), ("1:,:9,2:", 2)):
            want = volumes.crop_downsample(whole, crop, factor)
            got = load_file(path, crop=crop, downsample=factor)
            np.testing.assert_array_equal(got.data, want.data)
            np.testing.assert_allclose(got.origin, want.origin)
            assert got.spacing == want.spacing
            assert got.placement.startswith("NRRD orientation, in LPS: index axes")


def test_a_short_mapped_nrrd_is_refused_in_one_line(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    path = tmp_path / "short.nrrd"
    nrrd.write(str(path), np.zeros((4, 4, 4), np.uint8), {"encoding": "raw"})
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(VolumeError, match=r"short\.nrrd: expected 64 bytes of samples, the "
                                          r"data holds only 59: truncated"):
        load_file(path, crop="0:2,0:2,0:2")


def test_a_non_numeric_npy_is_refused_before_reading(tmp_path):
    path = tmp_path / "c.npy"
    np.save(path, np.ones((3, 3, 3), np.complex64))
    with pytest.raises(VolumeError, match=r"c\.npy: samples of type complex64 are not "
                                          r"supported"):
        load_file(path, downsample=1, crop=":,:,:")


MAPPED_SIZE = 48 << 20
"""Bytes of the file the memory tests map: 256 x 256 x 192 float32."""


@pytest.mark.parametrize("kind", ["raw", "npy", "nrrd"])
def test_a_mapped_file_is_read_in_part_within_bounded_memory(tmp_path, kind):
    """Peak traced memory ≈ the result plus a slab, well below the 48 MiB file."""
    data = np.random.default_rng(7).random((192, 256, 256), dtype=np.float32)
    if kind == "raw":
        path = _write_raw(tmp_path, data)
    elif kind == "npy":
        path = tmp_path / "big.npy"
        np.save(path, data)
    else:
        nrrd = pytest.importorskip("nrrd")
        path = tmp_path / "big.nrrd"
        nrrd.write(str(path), data, {"encoding": "raw"}, index_order="C")
    del data
    peaks = {}
    for crop, factor, bound in (("0:128,0:128,:", 1, MAPPED_SIZE // 2),
                                (None, 2, MAPPED_SIZE // 4),
                                ("64:192,:,96:", 4, MAPPED_SIZE // 32)):
        tracemalloc.start()
        try:
            part = load_file(path, crop=crop, downsample=factor)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        peaks[(crop, factor)] = peak / 2**20
        assert peak < bound, f"{kind} {crop} /{factor}: peak {peak / 2**20:.1f} MiB"
        assert peak > part.data.nbytes  # the measurement sees the result
    print(kind, {k: f"{v:.1f} MiB" for k, v in peaks.items()})


def test_a_whole_file_bigger_than_memory_can_be_read_in_part(tmp_path, monkeypatch):
    """The memory check counts the part's bytes, not the file's."""
    from isolume.volumes.io import common

    path = _write_raw(tmp_path, np.zeros((64, 64, 64), np.uint8))
    monkeypatch.setattr(common, "available_memory", lambda: 100_000)
    with pytest.raises(VolumeError, match="memory available"):
        load_file(path)
    assert load_file(path, crop="0:16,0:16,0:16").shape_xyz == (16, 16, 16)
    assert load_file(path, downsample=4).shape_xyz == (16, 16, 16)
    with pytest.raises(VolumeError, match=r"reading 32 x 32 x 32 voxels needs "):
        load_file(path, downsample=2)


# ---------------------------------------------------------------------------- command line


def _run(capsys, *argv):
    status = main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def test_info_reports_the_dims_of_the_volume_and_of_the_part(tmp_path, capsys):
    data = np.random.default_rng(8).integers(0, 255, (40, 50, 60)).astype(np.uint8)
    path = _write_raw(tmp_path, data)
    status, out, err = _run(capsys, "info", str(path), "--crop", "10:50,:,5:",
                            "--downsample", "3")
    assert status == 0, err
    assert "dims       13 x 16 x 11 (X x Y x Z)" in out
    assert "spacing    3, 3, 3" in out and "origin     11, 1, 6" in out
    assert ("cropped to voxels x 10:50, y 0:50, z 5:40 of 60 x 50 x 40; downsampled by 3: "
            "means of 3×3×3-voxel blocks (the last 1 along x, 2 along y, 2 along z left out"
            in out)


@pytest.mark.parametrize(("argv", "fragment"), [
    (["--crop", "1:2"], "--crop '1:2': expected X0:X1,Y0:Y1,Z0:Z1"),
    (["--crop", "0:99,:,:"], "x range 0:99 goes past the 60 voxels along x (volume dims "
                             "60 x 50 x 40)"),
    (["--downsample", "0"], "--downsample 0: expected an integer factor ≥ 1"),
    (["--level", "1"], "--level 1 only applies to OME-Zarr multiscale images"),
])
def test_bad_part_options_end_in_one_line(tmp_path, capsys, argv, fragment):
    path = _write_raw(tmp_path, np.zeros((40, 50, 60), np.uint8))
    status, _, err = _run(capsys, "info", str(path), *argv)
    assert status == 2 and fragment in err and err.count("\n") == 1, err


def test_crop_counts_before_up_and_works_on_synthetic_volumes(capsys):
    from isolume.app.cli import build_parser
    from isolume.app.options import load_volume

    args = build_parser().parse_args(["info", "synthetic:engine:48", "--crop", "4:40,:,2:",
                                      "--downsample", "2", "--up", "x"])
    plain = volumes.crop_downsample(volumes.load("synthetic:engine:48"), "4:40,:,2:", 2)
    got = load_volume(args)
    np.testing.assert_array_equal(got.data, volumes.turn_up(plain, "x").data)
    assert got.shape_xyz == (11, 15, 18)
    with pytest.raises(VolumeError, match="--level 0 gives the level of an OME-Zarr"):
        volumes.load("synthetic:sphere:16", level=0)


def test_a_synthetic_volume_takes_spacing_and_origin_and_refuses_file_options(capsys):
    """``--spacing`` and ``--origin`` place a synthetic volume as they place a file's (then
    ``--crop`` counts from there); ``--dims``, ``--dtype`` and ``--level`` describe files
    and are refused in one line, not left out silently."""
    plain = volumes.load("synthetic:torus:24")
    placed = volumes.load("synthetic:torus:24", spacing=(2.0, 1.0, 0.5), origin=(10, -4, 3))
    np.testing.assert_array_equal(placed.data, plain.data)
    assert placed.spacing == (2.0, 1.0, 0.5) and placed.origin == (10.0, -4.0, 3.0)
    assert placed.data_hash() != plain.data_hash()  # the hash covers the spacing
    status, out, err = _run(capsys, "info", "synthetic:torus:24", "--origin", "10,-4,3",
                            "--crop", "2:24,:,:")
    assert status == 0, err
    assert f"origin     {10 + 2 * plain.spacing[0]:g}, -4, 3" in out, out
    for argv, fragment in [(["--dims", "3,3,3"], "--dims 3,3,3 gives a raw file's size"),
                           (["--dtype", "uint8"], "--dtype uint8 gives a raw file's sample"),
                           (["--spacing", "0,1,1"], "spacing must be positive")]:
        status, _, err = _run(capsys, "info", "synthetic:torus:24", *argv)
        assert status == 2 and fragment in err and err.count("\n") == 1, (argv, err)
