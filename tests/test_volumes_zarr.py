"""Zarr and OME-Zarr volumes: samples, spacing and origin from the metadata, the level
asked for, the first index of other axes, only the chunks under a crop read (the others
are corrupted and must stay unread), and one-line errors naming the folder."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from isolume import volumes
from isolume.app.cli import main
from isolume.volumes.core import VolumeError
from isolume.volumes.io import load_file

zarr = pytest.importorskip("zarr")

SHAPE = (16, 12, 20)
"""(Z, Y, X) samples of level 0."""
CHUNK = 4


def _samples(shape=SHAPE, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 4000, shape).astype(np.uint16)


def _block_means(data: np.ndarray, f: int) -> np.ndarray:
    z, y, x = (n // f for n in data.shape)
    return data.reshape(z, f, y, f, x, f).mean(axis=(1, 3, 5), dtype=np.float64)


def _array(store, data: np.ndarray, fmt: int, chunks=None):
    """`data` written as a Zarr array at the folder `store`, in chunks of `CHUNK`."""
    arr = zarr.create_array(store=store, shape=data.shape, dtype=data.dtype,
                            chunks=chunks or (CHUNK,) * data.ndim, zarr_format=fmt)
    arr[...] = data
    return arr


def _member(group, name: str, data: np.ndarray, chunks=None):
    """`data` written as the array `name` of `group`."""
    arr = group.create_array(name, shape=data.shape, dtype=data.dtype,
                             chunks=chunks or (CHUNK,) * data.ndim)
    arr[...] = data
    return arr


def _ome_image(tmp_path, fmt: int, name="image.zarr"):
    """A two-level OME-Zarr image, axes c, z, y, x (2 channels, units micrometer): level 1
    holds the 2³ block means of level 0. Returns (path, channel 0 of level 0, of level 1)."""
    path = tmp_path / name
    group = zarr.open_group(str(path), mode="w", zarr_format=fmt)
    level0 = np.stack([_samples(), _samples(seed=1)])
    level1 = np.stack([_block_means(c, 2) for c in level0]).astype(np.float32)
    chunks = (1, CHUNK, CHUNK, CHUNK)
    _member(group, "0", level0, chunks)
    _member(group, "1", level1, chunks)
    axes = [{"name": "c", "type": "channel"},
            *({"name": n, "type": "space", "unit": "micrometer"} for n in "zyx")]
    datasets = [
        {"path": "0", "coordinateTransformations": [
            {"type": "scale", "scale": [1, 2.0, 0.5, 0.25]},
            {"type": "translation", "translation": [0, 10.0, -5.0, 3.0]}]},
        {"path": "1", "coordinateTransformations": [
            {"type": "scale", "scale": [1, 4.0, 1.0, 0.5]},
            {"type": "translation", "translation": [0, 11.0, -4.75, 3.125]}]},
    ]
    image = {"version": "0.4", "name": "img", "axes": axes, "datasets": datasets,
             "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1, 2.0]}]}
    if fmt == 2:
        group.attrs["multiscales"] = [image]
    else:
        group.attrs["ome"] = {"version": "0.5", "multiscales": [image]}
    return path, level0[0], level1[0]


# ---------------------------------------------------------------------------- plain arrays


@pytest.mark.parametrize("fmt", [2, 3])
def test_a_plain_array_loads_as_z_y_x(tmp_path, fmt):
    data = _samples()
    path = tmp_path / "plain.zarr"
    _array(str(path), data, fmt)
    vol = volumes.load(str(path))
    np.testing.assert_array_equal(vol.data, data.astype(np.float32))
    assert vol.spacing == (1.0, 1.0, 1.0) and vol.origin == (0.0, 0.0, 0.0)
    assert vol.name == "plain" and vol.source == str(path)
    assert vol.placement.endswith("gives no orientation (--up AXIS turns it); Zarr array")
    given = volumes.load(str(path), spacing=(0.5, 1, 2), origin=(1, 2, 3))
    assert given.spacing == (0.5, 1.0, 2.0) and given.origin == (1.0, 2.0, 3.0)


def test_leading_axes_of_length_one_are_dropped_and_the_suffix_is_optional(tmp_path):
    data = _samples((6, 5, 4))
    path = tmp_path / "no_suffix"
    _array(str(path), data[None, None], 3)
    np.testing.assert_array_equal(load_file(path).data, data.astype(np.float32))


@pytest.mark.parametrize("fmt", [2, 3])
def test_a_crop_reads_only_the_chunks_under_it(tmp_path, fmt):
    """Chunks outside the crop are overwritten with garbage: reading them would fail."""
    data = _samples()
    path = tmp_path / "lazy.zarr"
    _array(str(path), data, fmt)
    crop = "4:12,0:8,8:12"  # x chunks 1-2, y chunks 0-1, z chunks 2
    want = data[8:12, 0:8, 4:12]
    spoiled = _spoil_chunks_outside(path, fmt, {0: {2}, 1: {0, 1}, 2: {1, 2}})
    assert spoiled == 4 * 3 * 5 - 1 * 2 * 2  # of 4 x 3 x 5 chunks (z, y, x)
    got = load_file(path, crop=crop)
    np.testing.assert_array_equal(got.data, want.astype(np.float32))
    np.testing.assert_allclose(load_file(path, crop=crop, downsample=2).data,
                               _block_means(want, 2), rtol=1e-6)
    with pytest.raises(VolumeError, match=r"lazy\.zarr: cannot read the Zarr chunks of "
                                          r"samples \[z, y, x\]"):
        load_file(path)


def _spoil_chunks_outside(path, fmt: int, keep: dict[int, set[int]]) -> int:
    """Overwrite every chunk file of the array at `path` whose chunk index along some
    axis is not in `keep[axis]`; how many were spoiled."""
    spoiled = 0
    for chunk in path.rglob("*"):
        if not chunk.is_file() or chunk.name in (".zarray", ".zattrs", "zarr.json"):
            continue
        rel = chunk.relative_to(path)
        index = [int(p) for p in (rel.parts[1:] if fmt == 3 else rel.name.split("."))]
        if any(i not in keep[axis] for axis, i in enumerate(index)):
            chunk.write_bytes(b"not a chunk")
            spoiled += 1
    return spoiled


# ---------------------------------------------------------------------------- OME-Zarr


@pytest.mark.parametrize("fmt", [2, 3])
def test_an_ome_zarr_image_gives_spacing_origin_and_first_channel(tmp_path, fmt):
    path, level0, _ = _ome_image(tmp_path, fmt)
    vol = load_file(path)
    np.testing.assert_array_equal(vol.data, level0.astype(np.float32))
    # x, y, z; x scaled once more by the image's own transformation
    assert vol.spacing == (0.5, 0.5, 2.0)
    assert vol.origin == (6.0, -5.0, 10.0)
    assert vol.name == "image"
    assert ("OME-Zarr level 0 of 2 (dims X x Y x Z per level: 0: 20 x 12 x 16, "
            "1: 10 x 6 x 8); first index taken along the other axes: c 0 of 2; "
            "world units micrometer") in vol.placement


@pytest.mark.parametrize("fmt", [2, 3])
def test_the_level_is_chosen_and_placed_where_its_blocks_lie(tmp_path, fmt):
    path, _, level1 = _ome_image(tmp_path, fmt)
    coarse = load_file(path, level=1)
    np.testing.assert_array_equal(coarse.data, level1)
    assert coarse.spacing == (1.0, 1.0, 4.0) and coarse.origin == (6.25, -4.75, 11.0)
    assert "OME-Zarr level 1 of 2" in coarse.placement
    # the stored level is where downsampling level 0 puts its blocks
    down = load_file(path, downsample=2)
    np.testing.assert_allclose(down.data, coarse.data, rtol=1e-6)
    assert down.spacing == coarse.spacing
    np.testing.assert_allclose(down.origin, coarse.origin)
    part = load_file(path, level=1, crop="2:8,1:,:4")
    np.testing.assert_array_equal(part.data, level1[:4, 1:, 2:8])
    np.testing.assert_allclose(part.origin, np.add(coarse.origin, [2 * 1.0, 1 * 1.0, 0]))
    with pytest.raises(VolumeError, match=r"image\.zarr: --level 2: this OME-Zarr image has "
                                          r"2 level\(s\), 0 to 1"):
        load_file(path, level=2)


def test_axes_in_another_order_and_older_metadata(tmp_path):
    """Space axes named x, y, z in any order are put in z, y, x order; NGFF 0.1-0.2 (no
    axes) means t, c, z, y, x."""
    data = _samples((6, 5, 4))  # z, y, x
    path = tmp_path / "xyz.zarr"
    group = zarr.open_group(str(path), mode="w", zarr_format=2)
    _member(group, "s0", data.transpose(2, 1, 0).copy())
    group.attrs["multiscales"] = [{"version": "0.4", "axes": ["x", "y", "z"], "datasets": [
        {"path": "s0", "coordinateTransformations": [
            {"type": "scale", "scale": [0.1, 0.2, 0.3]}]}]}]
    vol = load_file(path)
    np.testing.assert_array_equal(vol.data, data.astype(np.float32))
    np.testing.assert_allclose(vol.spacing, (0.1, 0.2, 0.3))
    old = tmp_path / "old.zarr"
    group = zarr.open_group(str(old), mode="w", zarr_format=2)
    _member(group, "0", data[None, None])
    group.attrs["multiscales"] = [{"version": "0.2", "datasets": [{"path": "0"}]}]
    np.testing.assert_array_equal(load_file(old).data, data.astype(np.float32))


def test_info_lists_the_levels(tmp_path, capsys):
    path, _, _ = _ome_image(tmp_path, 3)
    status = main(["info", str(path), "--level", "1", "--crop", "2:8,:,:"])
    out, err = capsys.readouterr()
    assert status == 0, err
    assert "dims       6 x 6 x 8 (X x Y x Z)" in out
    assert "OME-Zarr level 1 of 2" in out and "cropped to voxels x 2:8, y 0:6, z 0:8" in out


# ---------------------------------------------------------------------------- errors


def _error(path, **options) -> str:
    with pytest.raises(VolumeError) as info:
        load_file(path, **options)
    message = str(info.value)
    assert message.startswith(str(path)) and "\n" not in message, message
    return message


def test_not_a_zarr_folder(tmp_path):
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    assert "not a Zarr folder: it holds none of .zarray, .zgroup, zarr.json" in _error(empty)
    file = tmp_path / "file.zarr"
    file.write_bytes(b"zip?")
    assert "a Zarr store must be a folder" in _error(file)


def test_a_2d_array_and_a_2d_image(tmp_path):
    flat = tmp_path / "flat.zarr"
    _array(str(flat), _samples((5, 6)), 3)
    assert "expected a 3-D Zarr array [z, y, x], got shape (5, 6)" in _error(flat)
    image = tmp_path / "image2d.zarr"
    group = zarr.open_group(str(image), mode="w", zarr_format=2)
    _member(group, "0", _samples((5, 6)))
    group.attrs["multiscales"] = [{"version": "0.4", "datasets": [{"path": "0"}],
                                   "axes": [{"name": "y"}, {"name": "x"}]}]
    assert "OME-Zarr axes y, x: expected space axes z, y and x" in _error(image)


@pytest.mark.parametrize("dtype", [np.complex64, np.dtype("S4")])
def test_unsupported_sample_types(tmp_path, dtype):
    path = tmp_path / "odd.zarr"
    arr = zarr.create_array(store=str(path), shape=(4, 4, 4), dtype=dtype, zarr_format=2)
    assert arr.shape == (4, 4, 4)
    message = _error(path)
    assert "samples of type" in message and "expected integers, floats or booleans" in message


def test_a_group_without_multiscales_names_its_arrays(tmp_path):
    path = tmp_path / "group.zarr"
    _member(zarr.open_group(str(path), mode="w", zarr_format=3), "raw", _samples((4, 4, 4)))
    message = _error(path)
    assert "a Zarr group without OME-Zarr multiscales metadata (holding raw)" in message
    assert f"pass one of them as {path}/NAME" in message
    np.testing.assert_array_equal(load_file(path / "raw").data.shape, (4, 4, 4))


def test_bad_transformations_and_levels_of_plain_arrays(tmp_path):
    path, _, _ = _ome_image(tmp_path, 2)
    attrs = zarr.open_group(str(path), mode="r+").attrs
    image = attrs["multiscales"][0]
    image["datasets"][0]["coordinateTransformations"] = [{"type": "scale", "scale": [1, 2]}]
    attrs["multiscales"] = [image]
    assert "OME-Zarr scale [1, 2]: expected 4 finite numbers, one per axis" in _error(path)
    plain = tmp_path / "plain.zarr"
    _array(str(plain), _samples((4, 4, 4)), 3)
    assert "--level 1: a plain Zarr array has one level (0)" in _error(plain, level=1)


@pytest.mark.parametrize("fmt", [2, 3])
def test_a_dataset_path_naming_a_group_is_refused(tmp_path, fmt):
    path = tmp_path / "image.zarr"
    group = zarr.open_group(str(path), mode="w", zarr_format=fmt)
    _member(group, "0", _samples((4, 4, 4)))
    group.create_group("1")
    group.attrs["multiscales"] = [{"version": "0.4", "axes": [{"name": n} for n in "zyx"],
                                   "datasets": [{"path": "0"}, {"path": "1"}]}]
    message = _error(path)
    assert "OME-Zarr level 1: dataset path '1' names a group, not an array" in message


def test_missing_zarr_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "plain.zarr"
    _array(str(path), _samples((4, 4, 4)), 3)
    monkeypatch.setitem(sys.modules, "zarr", None)
    with pytest.raises(VolumeError, match=r'plain\.zarr needs zarr: pip install '
                                          r'"isolume\[zarr\]"'):
        load_file(path)
