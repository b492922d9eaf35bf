"""Tests for volumes/io: a round trip through every format, and every bad input.

Every round trip writes an asymmetric (z, y, x) = (5, 7, 11) volume of distinct values
with anisotropic spacing and a non-zero origin, so a swapped axis or a lost header field
shows up as a failure.
"""

from __future__ import annotations

import bz2
import gzip
import io
import lzma
import os
import re
import signal
import struct
import sys
import tracemalloc
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

import isolume.volumes.io.common as vio_common
from isolume.volumes.core import STORED_TYPES, VolumeError
from isolume.volumes.io import load_file, parse_raw_name

SHAPE = (5, 7, 11)  # z, y, x
SPACING = (0.5, 0.75, 2.0)  # x, y, z
ORIGIN = (-3.0, 4.5, 10.0)  # x, y, z
INDICES = np.array([[0, 0, 0], [4, 6, 10], [2, 3, 7], [1, 5, 2]])  # (k, j, i)

SHARED_VOLUMES = Path(__file__).resolve().parents[2] / "shared" / "data" / "volumes"
CTHEAD = SHARED_VOLUMES / "CThead_256x256x113_uint16.raw.gz"


def sample_data(dtype: str = "int16") -> np.ndarray:
    """(5, 7, 11) array of distinct values 0..384, [z, y, x]."""
    return np.arange(np.prod(SHAPE)).reshape(SHAPE).astype(dtype)


def assert_volume(vol, expected, spacing=SPACING, origin=ORIGIN, name=None) -> None:
    """Same samples in [z, y, x] order, and the world position of voxels as written."""
    assert vol.data.shape == SHAPE
    assert vol.data.dtype in STORED_TYPES  # the file's type, or float32 (e.g. rescaled)
    np.testing.assert_array_equal(vol.data, np.asarray(expected, np.float32))
    world = vol.index_to_world(INDICES)
    want = np.asarray(origin) + INDICES[:, ::-1] * np.asarray(spacing)
    np.testing.assert_allclose(world, want, rtol=1e-6, atol=1e-9)
    if name is not None:
        assert vol.name == name


def load_error(path, *fragments, named=None, **options) -> str:
    """load_file(path) must raise a one-line VolumeError naming the file (or `named`) and
    fragments."""
    with pytest.raises(VolumeError, match=re.escape(str(named or path))) as info:
        load_file(path, **options)
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"
    return message


def refused_cheaply(path, *fragments, named=None, **options) -> str:
    """`load_error` (the message naming `named`, else `path`), the peak of memory traced
    while loading below 8 MiB."""
    tracemalloc.start()
    try:
        message = load_error(path, *fragments, named=named, **options)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, f"{peak} bytes traced for {message}"
    return message


# --------------------------------------------------------------------------- raw


def test_parse_raw_name_open_scivis_examples():
    assert parse_raw_name("engine_zfp_256x256x128_uint8.raw.gz") == (
        "engine_zfp",
        (256, 256, 128),
        np.dtype("uint8"),
    )
    stem, dims, dtype = parse_raw_name("CThead_256x256x113_uint16.raw.gz")
    assert (stem, dims, dtype) == ("CThead", (256, 256, 113), np.dtype("<u2"))
    stem, dims, dtype = parse_raw_name("/some/dir/headsq_quarter_64x64x93_int16.raw")
    assert (stem, dims, dtype) == ("headsq_quarter", (64, 64, 93), np.dtype("<i2"))
    assert parse_raw_name("a_2x3x4_float.raw")[2] == np.dtype("<f4")
    assert parse_raw_name("a_2x3x4_double.raw")[2] == np.dtype("<f8")
    assert parse_raw_name("skull.raw") is None
    assert parse_raw_name("skull_256x256x256_uint8.nrrd") is None


def test_parse_raw_name_unknown_dtype():
    with pytest.raises(VolumeError, match=r"x_2x3x4_int64\.raw.*'int64'") as info:
        parse_raw_name("x_2x3x4_int64.raw")
    assert "uint8" in str(info.value)


def test_raw_round_trip(tmp_path):
    data = sample_data("int16")
    path = tmp_path / "vol_11x7x5_int16.raw"
    path.write_bytes(data.astype("<i2").tobytes())
    vol = load_file(path, spacing=SPACING, origin=ORIGIN)
    assert_volume(vol, data, name="vol")
    assert vol.source == str(path)
    default = load_file(path)
    assert default.spacing == (1.0, 1.0, 1.0)
    assert default.origin == (0.0, 0.0, 0.0)


def test_raw_gz_round_trip(tmp_path):
    data = sample_data("uint16") * 100
    path = tmp_path / "engine_zfp_11x7x5_uint16.raw.gz"
    path.write_bytes(gzip.compress(data.astype("<u2").tobytes()))
    assert_volume(load_file(path, spacing=SPACING, origin=ORIGIN), data, name="engine_zfp")


def test_raw_float32_writable(tmp_path):
    data = sample_data("float32") / 7
    path = tmp_path / "f_11x7x5_float32.raw"
    path.write_bytes(data.astype("<f4").tobytes())
    vol = load_file(path, spacing=SPACING, origin=ORIGIN)
    assert_volume(vol, data)
    assert vol.data.flags.writeable


def test_raw_explicit_dims_dtype_and_big_endian(tmp_path):
    data = sample_data("float64") / 3
    path = tmp_path / "scan.dat"  # unknown extension, read as raw because both are given
    path.write_bytes(data.astype(">f8").tobytes())
    vol = load_file(
        path, dims=(11, 7, 5), dtype="double", endian="big", spacing=SPACING, origin=ORIGIN
    )
    assert_volume(vol, data, name="scan")


def test_raw_explicit_dims_dtype_override_name(tmp_path):
    data = sample_data("int16")
    path = tmp_path / "wrong_3x3x3_uint8.raw"
    path.write_bytes(data.astype("<i2").tobytes())
    vol = load_file(path, dims=(11, 7, 5), dtype="int16", spacing=SPACING, origin=ORIGIN)
    assert_volume(vol, data, name="wrong")


def test_raw_without_pattern_needs_dims_and_dtype(tmp_path):
    path = tmp_path / "plain.raw"
    path.write_bytes(bytes(8))
    load_error(path, "--dims", "--dtype")
    load_error(path, "--dims", dims=(2, 2, 2))


def test_raw_truncated(tmp_path):
    path = tmp_path / "vol_11x7x5_int16.raw"
    path.write_bytes(bytes(700))
    load_error(path, "11*7*5*2 = 770 bytes", "700", "truncated")


def test_raw_gz_truncated(tmp_path):
    path = tmp_path / "vol_11x7x5_int16.raw.gz"
    path.write_bytes(gzip.compress(bytes(700)))
    load_error(path, "11*7*5*2 = 770 bytes", "only 700 decompressed bytes")


def test_raw_dims_in_name_do_not_match_size(tmp_path):
    path = tmp_path / "vol_4x4x4_uint8.raw"
    path.write_bytes(bytes(100))
    load_error(path, "4*4*4*1 = 64 bytes", "got 100 bytes", "in the file name")


def test_raw_unknown_dtype_in_name(tmp_path):
    path = tmp_path / "vol_4x4x4_int64.raw"
    path.write_bytes(bytes(512))
    load_error(path, "'int64'", "in the file name", "float32")


def test_raw_unknown_dtype_given(tmp_path):
    path = tmp_path / "vol.raw"
    path.write_bytes(bytes(64))
    load_error(path, "'complex64'", "given", dims=(4, 4, 4), dtype="complex64")


@pytest.mark.parametrize("dims", [(4, 0, 4), (4, -2, 4)])
def test_raw_non_positive_dims(tmp_path, dims):
    path = tmp_path / "vol.raw"
    path.write_bytes(bytes(64))
    load_error(path, "dims given", str(dims), dims=dims, dtype="uint8")


def test_raw_zero_dims_in_name(tmp_path):
    path = tmp_path / "vol_4x0x4_uint8.raw"
    path.write_bytes(bytes(16))
    load_error(path, "(4, 0, 4)", "positive")


def test_raw_bad_dims_type_and_endian(tmp_path):
    path = tmp_path / "vol.raw"
    path.write_bytes(bytes(64))
    load_error(path, "three integers", "2.5", dims=(4, 2.5, 4), dtype="uint8")
    load_error(path, "'middle'", "little", dims=(4, 4, 4), dtype="uint8", endian="middle")


@pytest.mark.parametrize("payload", [b"this is not gzip data at all", b"gz"])
def test_raw_corrupt_gzip(tmp_path, payload):
    path = tmp_path / "vol_4x4x4_uint8.raw.gz"
    path.write_bytes(payload)
    load_error(path, "corrupt gzip")


def test_raw_gzip_cut_short(tmp_path):
    path = tmp_path / "vol_4x4x4_uint8.raw.gz"
    path.write_bytes(gzip.compress(bytes(range(64)))[:-12])
    load_error(path, "corrupt gzip")


def test_non_positive_spacing_names_file(tmp_path):
    path = tmp_path / "vol_4x4x4_uint8.raw"
    path.write_bytes(bytes(64))
    load_error(path, "spacing", "-1.0", spacing=(1.0, -1.0, 1.0))
    load_error(path, "spacing", "0.0", spacing=(0.0, 1.0, 1.0))


def test_raw_sizes_given_are_named_as_given(tmp_path):
    path = tmp_path / "vol_4x4x4_uint8.raw"
    path.write_bytes(bytes(64))
    for options, source in (({"dims": (4, 4, 5)}, "--dims given"),
                            ({"dtype": "uint16"}, "--dtype given"),
                            ({"dims": (4, 4, 5), "dtype": "uint8"}, "--dims/--dtype given")):
        message = load_error(path, "truncated", source, **options)
        assert "dims/dtype in the file name" not in message


@pytest.mark.parametrize("crop", [None, "0:4,0:4,0:2"])
def test_raw_int32_and_float64_beyond_float32(tmp_path, capsys, crop):
    """Whole or cropped (read in part), samples that float32 rounds are said once, and
    values beyond its range refused as such."""
    data = np.full((4, 4, 4), 16777216, "<i4")
    data[1::2] = 16777217
    path = tmp_path / "labels_4x4x4_int32.raw"
    path.write_bytes(data.tobytes())
    assert load_file(path, crop=crop).data.dtype == np.float32
    err = capsys.readouterr().err
    assert err.startswith(f"isolume: warning: {path}: int32") and err.count("\n") == 1
    assert "16777217 became 16777216" in err
    path = tmp_path / "wide_4x4x4_float64.raw"
    path.write_bytes(np.where(data > 16777216, 1e300, 0.0).astype("<f8").tobytes())
    load_error(path, "value 1e+300 (float64) is beyond float32's range", crop=crop)


# --------------------------------------------------------------------------- files


def test_missing_file(tmp_path):
    load_error(tmp_path / "nope_4x4x4_uint8.raw", "no such file")


def test_unknown_extension_lists_supported(tmp_path):
    path = tmp_path / "volume.xyz"
    path.write_bytes(bytes(64))
    load_error(path, "'.xyz'", ".nrrd", ".nii.gz", ".mhd", "DICOM", "--dims")


def test_unreadable_file_chmod(tmp_path):
    path = tmp_path / "vol_4x4x4_uint8.raw"
    path.write_bytes(bytes(64))
    path.chmod(0)
    try:
        if os.access(path, os.R_OK):
            pytest.skip("running as a user who can read mode-000 files (root)")
        load_error(path, "permission denied")
    finally:
        path.chmod(0o644)


def test_unreadable_file_reported(tmp_path, monkeypatch):
    path = tmp_path / "vol_4x4x4_uint8.raw"
    path.write_bytes(bytes(64))

    def refuse(file, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(file))

    monkeypatch.setattr(vio_common, "open", refuse, raising=False)
    load_error(path, "permission denied")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    path = tmp_path / "pipe_2x2x2_uint8.raw"
    os.mkfifo(path)

    def waited(signum, frame):
        raise TimeoutError("load_file waited for a writer")

    before = signal.signal(signal.SIGALRM, waited)
    signal.alarm(5)
    try:
        load_error(path, "FIFO", "not a regular file")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)


def test_options_only_for_raw(tmp_path):
    path = tmp_path / "a.npy"
    np.save(path, sample_data())
    load_error(path, "--dims", ".npy", dims=(11, 7, 5))


def test_missing_optional_library(tmp_path, monkeypatch):
    path = tmp_path / "foo.nrrd"
    path.write_bytes(b"NRRD0004\n")
    monkeypatch.setitem(sys.modules, "nrrd", None)
    message = load_error(path, "needs pynrrd")
    assert message == f'reading {path} needs pynrrd: pip install "isolume[nrrd]"'


# --------------------------------------------------------------------------- NRRD


def nrrd_header() -> dict:
    return {
        "space": "left-posterior-superior",
        "space directions": np.diag(SPACING),
        "space origin": np.array(ORIGIN),
    }


def test_nrrd_round_trip(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    data = sample_data("int16")
    path = tmp_path / "head.nrrd"
    nrrd.write(str(path), data, nrrd_header(), index_order="C")
    assert_volume(load_file(path), data, name="head")


def test_nhdr_detached_round_trip(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    data = sample_data("float32") * 0.25
    path = tmp_path / "head.nhdr"
    nrrd.write(str(path), data, nrrd_header(), index_order="C", detached_header=True)
    assert len(list(tmp_path.iterdir())) == 2  # header + separate data file
    assert_volume(load_file(path), data, name="head")


def test_nrrd_spacings_field(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    data = sample_data("uint8")
    path = tmp_path / "plain.nrrd"
    nrrd.write(str(path), data, {"spacings": np.array(SPACING)}, index_order="C")
    assert_volume(load_file(path, origin=ORIGIN), data)


def test_nrrd_corrupt_header(tmp_path):
    pytest.importorskip("nrrd")
    path = tmp_path / "bad.nrrd"
    path.write_bytes(
        b"NRRD0004\ntype: banana\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n" + bytes(8)
    )
    load_error(path, "not a valid NRRD file", "banana")
    path.write_bytes(b"definitely not nrrd\n")
    load_error(path, "not a valid NRRD file")


def test_nrrd_not_3d(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    path = tmp_path / "flat.nrrd"
    nrrd.write(str(path), np.zeros((4, 5), np.uint8), index_order="C")
    load_error(path, "3-D", "dimension 2")


NRRD_HEAD = b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n"


def test_nrrd_empty_file(tmp_path):
    pytest.importorskip("nrrd")
    path = tmp_path / "empty.nrrd"
    path.write_bytes(b"")
    load_error(path, "not a valid NRRD file", "empty")


def test_nrrd_errors_are_said_once_and_whole(tmp_path, monkeypatch):
    pytest.importorskip("nrrd")
    path = tmp_path / "short.nrrd"
    path.write_bytes(NRRD_HEAD + b"\n" + bytes(10))
    message = load_error(path, "expected 64 bytes of samples", "ends after 10")
    assert "not a valid NRRD file" not in message and "VolumeError" not in message
    monkeypatch.setattr(vio_common, "available_memory", lambda: 10)
    message = load_error(path, "needs", "--crop", "read without the whole file")
    assert message.endswith("Zarr)") and message.count(str(path)) == 1


@pytest.mark.parametrize("crop", [None, "0:2,0:2,0:2"])
def test_nrrd_missing_detached_data_file(tmp_path, crop):
    pytest.importorskip("nrrd")
    path = tmp_path / "head.nhdr"
    path.write_bytes(NRRD_HEAD + b"data file: nothere.raw\n\n")
    load_error(path, "detached data file 'nothere.raw' is missing",
               str(tmp_path / "nothere.raw"), crop=crop)


@pytest.mark.parametrize("row", [b"(nan,0,0)", b"(inf,0,0)", b"(1,nan,0)"])
def test_nrrd_non_finite_space_directions(tmp_path, row):
    pytest.importorskip("nrrd")
    path = tmp_path / "odd.nrrd"
    path.write_bytes(NRRD_HEAD + b"space: left-posterior-superior\nspace directions: " + row
                     + b" (0,1,0) (0,0,1)\n\n" + bytes(64))
    load_error(path, "space directions vector 1", "finite")


NRRD_2X2X2 = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\n"
"""A header of 2*2*2 uint8 samples, its encoding and the rest to follow."""


@pytest.mark.parametrize("case", ["bzip2", "gzip detached", "raw detached"])
def test_nrrd_data_that_hold_more_than_the_header_are_refused_unread(tmp_path, case):
    """32 MiB of data behind a header of 8 bytes of samples: refused having read (and
    decompressed) at most a chunk of them."""
    pytest.importorskip("nrrd")
    path = tmp_path / "bomb.nhdr"
    where = tmp_path / "bomb.data"
    if case == "bzip2":
        where = path
        path.write_bytes(f"{NRRD_2X2X2}encoding: bzip2\n\n".encode()
                         + bz2.compress(bytes(32 << 20)))
    elif case == "gzip detached":
        where.write_bytes(gzip.compress(bytes(32 << 20), 1))
        path.write_text(f"{NRRD_2X2X2}encoding: gzip\ndata file: bomb.data\n\n")
    else:
        with open(where, "wb") as f:
            f.truncate(32 << 20)
        path.write_text(f"{NRRD_2X2X2}encoding: raw\ndata file: bomb.data\n\n")
    refused_cheaply(path, "expected 8 ", "bytes of samples", "holds more", named=where)


@pytest.mark.parametrize("detached", [False, True])
@pytest.mark.parametrize("encoding", ["raw", "gzip", "bzip2"])
def test_nrrd_encodings_attached_and_detached_read_as_pynrrd_writes_them(tmp_path, encoding,
                                                                        detached):
    nrrd = pytest.importorskip("nrrd")
    data = sample_data("uint16")
    for endian in ("little", "big"):
        path = tmp_path / f"v_{endian}.{'nhdr' if detached else 'nrrd'}"
        nrrd.write(str(path), data, {"encoding": encoding, "endian": endian},
                   index_order="C", detached_header=detached)
        np.testing.assert_array_equal(load_file(path).data, data.astype(np.float32))


@pytest.mark.parametrize(("fields", "payload"), [
    ("encoding: raw\nline skip: 2\n", b"abc\n" + b"x" * 3000 + b"\n" + bytes(range(8))),
    ("encoding: raw\nbyte skip: 3\n", b"abc" + bytes(range(8))),
    ("encoding: raw\nbyte skip: -1\n", b"leading" + bytes(range(8))),
    ("encoding: gzip\nbyte skip: 3\n", gzip.compress(b"abc" + bytes(range(8)))),
    ("encoding: bzip2\nbyte skip: 3\n", bz2.compress(b"abc" + bytes(range(8)))),
    ("encoding: bzip2\n", bz2.compress(bytes(range(3))) + bz2.compress(bytes(range(3, 8)))),
], ids=["line skip", "raw byte skip", "raw byte skip -1", "gzip byte skip", "bzip2 byte skip",
        "two bzip2 streams"])
def test_nrrd_skips_and_concatenated_streams(tmp_path, fields, payload):
    """Line skips count lines of the file, byte skips bytes of the decompressed data
    (-1: the raw samples are the file's last bytes); bzip2 streams may follow one another."""
    pytest.importorskip("nrrd")
    path = tmp_path / "skips.nrrd"
    path.write_bytes(f"{NRRD_2X2X2}{fields}\n".encode() + payload)
    np.testing.assert_array_equal(load_file(path).data.ravel(), np.arange(8))


@pytest.mark.parametrize(("fields", "payload", "fragments"), [
    ("encoding: bzip2\n", bz2.compress(bytes(8))[:-5], ("ended before the end-of-stream",)),
    ("encoding: bzip2\n", b"not bzip2 at all", ("Invalid data stream",)),
    ("encoding: bzip2\n", bz2.compress(bytes(5)), ("expected 8 decompressed", "after 5")),
    ("encoding: bzip2\nbyte skip: -1\n", bz2.compress(bytes(8)),
     ("byte skip -1 with bzip2", "only with raw encoding")),
    ("encoding: raw\nline skip: -2\n", bytes(8), ("line skip -2", "at least 0")),
], ids=["bzip2 cut short", "not bzip2", "bzip2 of fewer samples",
        "bzip2 byte skip -1", "negative line skip"])
def test_nrrd_bad_bzip2_data_and_skips(tmp_path, fields, payload, fragments):
    pytest.importorskip("nrrd")
    path = tmp_path / "bad.nrrd"
    path.write_bytes(f"{NRRD_2X2X2}{fields}\n".encode() + payload)
    load_error(path, *fragments)


@pytest.mark.parametrize("crop", [None, "0:2,0:2,0:2"])
def test_nrrd_sizes_beyond_int64_are_named_whole(tmp_path, crop):
    """7 * 2**62 * 8 samples: 0 in int64 arithmetic."""
    pytest.importorskip("nrrd")
    path = tmp_path / "huge.nrrd"
    path.write_bytes(f"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 7 {2**62} 8\n"
                     "encoding: raw\n\n".encode() + bytes(8))
    said = ((f"expected {7 * 2**62 * 8} bytes", "holds only 8") if crop else
            (f"sizes 7 {2**62} 8 uchar needs", "memory available"))
    load_error(path, *said, crop=crop)


# --------------------------------------------------------------------------- MetaImage


def write_metaimage(
    path: Path,
    data: np.ndarray,
    *,
    data_file: str = "LOCAL",
    compressed: bool = False,
    msb: bool = False,
    spacing_key: str = "ElementSpacing",
    origin_key: str = "Offset",
) -> None:
    """Write a MetaImage header (+ LOCAL or separate raw data) for int16 ``data``."""
    payload = data.astype(">i2" if msb else "<i2").tobytes()
    if compressed:
        payload = zlib.compress(payload)
    z, y, x = data.shape
    lines = [
        "ObjectType = Image",
        "NDims = 3",
        f"DimSize = {x} {y} {z}",
        "ElementType = MET_SHORT",
        f"{spacing_key} = {' '.join(map(str, SPACING))}",
        f"{origin_key} = {' '.join(map(str, ORIGIN))}",
        f"BinaryDataByteOrderMSB = {msb}",
        f"CompressedData = {compressed}",
    ]
    if compressed:
        lines.append(f"CompressedDataSize = {len(payload)}")
    lines.append(f"ElementDataFile = {data_file}")
    header = ("\n".join(lines) + "\n").encode()
    if data_file == "LOCAL":
        path.write_bytes(header + payload)
    else:
        path.write_bytes(header)
        (path.parent / data_file).write_bytes(payload)


def test_mhd_with_raw_round_trip(tmp_path):
    data = sample_data("int16") - 50
    path = tmp_path / "ct.mhd"
    write_metaimage(path, data, data_file="ct.raw")
    assert_volume(load_file(path), data, name="ct")


def test_mha_local_big_endian_round_trip(tmp_path):
    data = sample_data("int16")
    path = tmp_path / "ct.mha"
    write_metaimage(path, data, msb=True, spacing_key="ElementSize", origin_key="Origin")
    assert_volume(load_file(path), data, name="ct")


def test_mha_compressed_round_trip(tmp_path):
    data = sample_data("int16")
    path = tmp_path / "ct.mha"
    write_metaimage(path, data, compressed=True)
    assert_volume(load_file(path), data)


def test_mha_corrupt_compressed_data(tmp_path):
    path = tmp_path / "ct.mha"
    write_metaimage(path, sample_data(), compressed=True)
    content = path.read_bytes()
    path.write_bytes(content[: content.index(b"LOCAL\n") + 6] + b"garbage" * 20)
    load_error(path, "corrupt compressed MetaImage data")


def test_mhd_missing_data_file(tmp_path):
    path = tmp_path / "ct.mhd"
    write_metaimage(path, sample_data(), data_file="ct.raw")
    (tmp_path / "ct.raw").unlink()
    load_error(path, "'ct.raw' not found")


def test_mhd_short_data_file(tmp_path):
    path = tmp_path / "ct.mhd"
    write_metaimage(path, sample_data(), data_file="ct.raw")
    (tmp_path / "ct.raw").write_bytes(bytes(10))
    with pytest.raises(VolumeError, match=re.escape(str(tmp_path / "ct.raw"))) as info:
        load_file(path)
    assert "11*7*5*2 = 770 bytes" in str(info.value)
    assert "got 10 bytes" in str(info.value)


def test_mhd_bad_header_values(tmp_path):
    path = tmp_path / "ct.mhd"
    write_metaimage(path, sample_data(), data_file="ct.raw")
    header = path.read_text()
    path.write_text(header.replace("MET_SHORT", "MET_BANANA"))
    load_error(path, "'MET_BANANA'", "MET_USHORT")
    path.write_text(
        header.replace("NDims = 3", "NDims = 2").replace("DimSize = 11 7 5", "DimSize = 11 7")
    )
    load_error(path, "NDims = 2", "3-D")
    path.write_text(header.replace("ElementDataFile = ct.raw\n", ""))
    load_error(path, "no ElementDataFile")
    path.write_text("this is not a header\n")
    load_error(path, "'this is not a header'", "Key = Value")


@pytest.mark.parametrize("compressed", [False, True])
def test_mhd_data_file_is_not_read_past_dimsize(tmp_path, compressed):
    """A 64 MiB (sparse) data file behind DimSize 11 7 5 is refused having read at most
    a chunk of it."""
    path = tmp_path / "ct.mhd"
    write_metaimage(path, sample_data(), data_file="ct.raw", compressed=compressed)
    if compressed:
        path.write_text(path.read_text().replace("CompressedDataSize", "Comment"))
    with open(tmp_path / "ct.raw", "wb") as f:
        f.truncate(64 << 20)
    said = "corrupt compressed MetaImage data" if compressed else "got 67108864 bytes"
    tracemalloc.start()
    try:
        with pytest.raises(VolumeError, match=re.escape(f"{tmp_path / 'ct.raw'}: ")) as info:
            load_file(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert said in str(info.value)
    assert peak < 16 << 20, f"{peak} bytes traced for {info.value}"


def test_mha_header_size(tmp_path):
    data = sample_data()
    path = tmp_path / "ct.mha"
    write_metaimage(path, data)
    header, payload = path.read_bytes().split(b"LOCAL\n")
    for size, skipped in ((3, b"abc"), (-1, b"leading bytes")):
        path.write_bytes(header.replace(b"ElementDataFile", f"HeaderSize = {size}\n"
                                        "ElementDataFile".encode()) + b"LOCAL\n" + skipped
                         + payload)
        assert_volume(load_file(path), data)
    for size in ("-5", "2.5"):
        path.write_bytes(header.replace(b"ElementDataFile", f"HeaderSize = {size}\n"
                                        "ElementDataFile".encode()) + b"LOCAL\n" + payload)
        load_error(path, f"HeaderSize = '{size}'", "at least 0", "-1")


@pytest.mark.parametrize("value", ["inf", "3.7", "nan"])
def test_mha_ndims_must_be_three(tmp_path, value):
    path = tmp_path / "ct.mha"
    write_metaimage(path, sample_data())
    path.write_bytes(path.read_bytes().replace(b"NDims = 3", f"NDims = {value}".encode()))
    load_error(path, f"NDims = {value}", "expected a 3-D MetaImage (NDims = 3")


@pytest.mark.parametrize("size_field", [True, False])
def test_mha_compressed_data_followed_by_more_bytes(tmp_path, size_field):
    path = tmp_path / "ct.mha"
    write_metaimage(path, sample_data(), compressed=True)
    if not size_field:
        path.write_bytes(path.read_bytes().replace(b"CompressedDataSize", b"Comment"))
    stream = len(zlib.compress(sample_data().astype("<i2").tobytes()))
    with open(path, "ab") as f:
        f.write(b"JUNK" * 1000)
    load_error(path, "expected the compressed samples to end the file",
               f"4000 bytes follow their {stream}-byte stream")


# --------------------------------------------------------------------------- NIfTI


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_round_trip(tmp_path, suffix):
    nib = pytest.importorskip("nibabel")
    data = sample_data("int16")
    affine = np.diag([*SPACING, 1.0])
    affine[:3, 3] = ORIGIN
    path = tmp_path / f"brain{suffix}"
    nib.save(nib.Nifti1Image(data.transpose(2, 1, 0), affine), str(path))  # [i, j, k] = [x, y, z]
    assert_volume(load_file(path, orientation=False), data, name="brain")


def test_nifti_corrupt(tmp_path):
    pytest.importorskip("nibabel")
    path = tmp_path / "brain.nii"
    path.write_bytes(b"not a nifti file" * 30)
    load_error(path, "NIfTI")


def write_nifti(path: Path, dims, datatype: int = 2, samples: bytes = bytes(4096)) -> None:
    """A NIfTI-1 file (gzip-compressed for ``.gz``) whose header says `dims` and
    `datatype` whatever the `samples` that follow it."""
    nib = pytest.importorskip("nibabel")
    header = nib.Nifti1Header()
    header.set_data_dtype(np.uint8)
    header["dim"][: len(dims) + 1] = [len(dims), *dims]
    header["datatype"] = datatype
    header["vox_offset"] = 352
    content = header.binaryblock + bytes(4) + samples
    path.write_bytes(gzip.compress(content) if path.name.endswith(".gz") else content)


@pytest.mark.parametrize(("suffix", "fragments"), [
    (".nii", ("need 100000000 bytes of samples from offset 352", "holds 4096")),
    (".nii.gz", ("expected 100000000 decompressed bytes", "ends after 4096")),
])
def test_nifti_dims_that_lie_are_refused_before_reading(tmp_path, suffix, fragments):
    path = tmp_path / f"lie{suffix}"
    write_nifti(path, (1000, 1000, 100))
    load_error(path, *fragments, "dims")


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_bad_dims_and_datatype(tmp_path, capfd, suffix):
    path = tmp_path / f"bad{suffix}"
    write_nifti(path, (30000, 30000, 30000))
    load_error(path, "dims 30000 30000 30000 uint8 needs", "memory available")
    write_nifti(path, (-16, 16, 16))
    load_error(path, "NIfTI dims (-16, 16, 16)", "positive")
    write_nifti(path, (16, 16, 16), datatype=9999)
    load_error(path, "9999", "invalid NIfTI header", "datatype")
    assert "9999" not in capfd.readouterr().err  # said once, by the error


def test_nifti_bytes_after_the_samples_are_refused(tmp_path):
    """Extensions between the header and vox_offset are read past; bytes after the
    samples, in the file or in the gzip stream, are refused."""
    nib = pytest.importorskip("nibabel")
    data = sample_data("int16")
    image = nib.Nifti1Image(data.transpose(2, 1, 0), np.eye(4))
    image.header.extensions.append(nib.nifti1.Nifti1Extension("comment", b"x" * 500))
    plain, packed = tmp_path / "brain.nii", tmp_path / "brain.nii.gz"
    nib.save(image, str(plain))
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    for path in (plain, packed):
        np.testing.assert_array_equal(load_file(path, orientation=False).data, data)
    offset = int(nib.load(str(plain)).dataobj.offset)
    assert offset > 352 + 500
    with open(plain, "ab") as f:
        f.write(bytes(4096))
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    load_error(plain, f"need {data.nbytes} bytes of samples from offset {offset} to the end",
               f"holds {data.nbytes + 4096}", "bytes follow the samples")
    load_error(packed, f"expected {data.nbytes} decompressed bytes", "holds more")


# --------------------------------------------------------------------------- NumPy


def test_npy_round_trip(tmp_path):
    data = sample_data("float64") / 5
    path = tmp_path / "field.npy"
    np.save(path, data)
    assert_volume(load_file(path, spacing=SPACING, origin=ORIGIN), data, name="field")
    default = load_file(path)
    assert default.spacing == (1.0, 1.0, 1.0) and default.origin == (0.0, 0.0, 0.0)


def test_npz_round_trip(tmp_path):
    data = sample_data("uint16")
    path = tmp_path / "field.npz"
    np.savez(path, data=data, spacing=np.array(SPACING), origin=np.array(ORIGIN))
    assert_volume(load_file(path), data, name="field")
    only = tmp_path / "only.npz"
    np.savez_compressed(only, density=data)
    assert_volume(load_file(only, spacing=SPACING, origin=ORIGIN), data)


def test_npy_not_3d(tmp_path):
    path = tmp_path / "flat.npy"
    np.save(path, np.zeros((4, 5)))
    load_error(path, "3-D", "(4, 5)")


def test_npy_corrupt_and_npz_ambiguous(tmp_path):
    path = tmp_path / "junk.npy"
    path.write_bytes(b"junk" * 10)
    load_error(path, "not a .npy array file", "junk")
    bad_zip = tmp_path / "junk.npz"
    bad_zip.write_bytes(b"junk" * 10)
    load_error(bad_zip, "not a .npz (zip) archive")
    npz = tmp_path / "two.npz"
    np.savez(npz, a=sample_data(), b=sample_data())
    load_error(npz, "['a', 'b']", "'data'")


def write_npy_header(f, shape, descr: str = "|u1") -> None:
    """A .npy version 1.0 header that says `shape` and `descr`, whatever follows it."""
    np.lib.format.write_array_header_1_0(
        f, {"descr": descr, "fortran_order": False, "shape": shape})


@pytest.mark.parametrize("crop", [None, "0:2,0:2,0:2"])
def test_npy_header_that_lies_about_its_shape(tmp_path, crop):
    path = tmp_path / "lie.npy"
    with open(path, "wb") as f:
        write_npy_header(f, (100000, 100000, 100000))
        f.write(bytes(4096))
    load_error(path, "expected 1000000000000000 bytes", "(100000, 100000, 100000)",
               "holds only 4096", crop=crop)


def test_npy_with_bytes_after_its_array(tmp_path):
    path = tmp_path / "long.npy"
    np.save(path, sample_data("uint8"))
    with open(path, "ab") as f:
        f.write(bytes(10))
    load_error(path, f"expected {np.prod(SHAPE)} bytes", f"holds {np.prod(SHAPE) + 10}")


def test_npz_member_header_that_lies_about_its_shape(tmp_path):
    path = tmp_path / "lie.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("data.npy", "w") as f:
            write_npy_header(f, (100000, 100000, 100000))
            f.write(bytes(4096))
    load_error(path, "[data]", "expected 1000000000000000 bytes", "holds only 4096")


def test_npz_that_is_not_a_zip(tmp_path):
    path = tmp_path / "fake.npz"
    path.write_bytes(b"PKhello")
    message = load_error(path, "not a valid .npz archive", "zip")
    assert "pickle" not in message


# --------------------------------------------------------------------------- TIFF


def test_tiff_multipage_round_trip(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    data = sample_data("uint16")
    path = tmp_path / "stack.tif"
    with tifffile.TiffWriter(path) as tw:
        for page in data:  # one 2-D page per z slice
            tw.write(page)
    assert_volume(load_file(path, spacing=SPACING, origin=ORIGIN), data, name="stack")


def test_tiff_imagej_spacing(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    data = sample_data("uint16")
    path = tmp_path / "stack.tiff"
    tifffile.imwrite(
        path,
        data,
        imagej=True,
        resolution=(1 / SPACING[0], 1 / SPACING[1]),
        metadata={"spacing": SPACING[2], "unit": "um", "axes": "ZYX"},
    )
    vol = load_file(path, origin=ORIGIN)
    np.testing.assert_allclose(vol.spacing, SPACING, rtol=1e-5)
    assert_volume(vol, data, spacing=vol.spacing)


def test_tiff_single_page_refused(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    path = tmp_path / "flat.tif"
    tifffile.imwrite(path, np.zeros((7, 11), np.uint8))
    load_error(path, "(7, 11)", "stack")


def test_tiff_folder_natural_order(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    data = sample_data("uint16")
    folder = tmp_path / "slices"
    folder.mkdir()
    # Lexicographic order would put slice10 before slice2.
    for number, page in zip([1, 2, 3, 9, 10], data, strict=True):
        tifffile.imwrite(folder / f"slice{number}.tif", page)
    (folder / "notes.txt").write_text("not a slice")
    loaded = load_file(folder, spacing=SPACING, origin=ORIGIN)
    assert_volume(loaded, data, name="slices")
    assert loaded.placement.startswith("as stored: the TIFF input gives no orientation")


def test_tiff_folder_mismatched_slice(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    folder = tmp_path / "slices"
    folder.mkdir()
    tifffile.imwrite(folder / "s1.tif", np.zeros((7, 11), np.uint8))
    tifffile.imwrite(folder / "s2.tif", np.zeros((7, 12), np.uint8))
    with pytest.raises(VolumeError, match=re.escape(str(folder / "s2.tif"))) as info:
        load_file(folder)
    assert "(7, 12)" in str(info.value) and "(7, 11)" in str(info.value)


def lying_tiff(path: Path, side: int, compression: str | int | None = None,
               pages: int = 3) -> None:
    """A stack of `pages` 4 x 4 uint8 pages of zeros whose every ImageWidth and
    ImageLength tag says `side`: compressed by tifffile (a codec's name), or (a TIFF
    Compression code) each page one strip of `encoded_zeros`, under that code."""
    tifffile = pytest.importorskip("tifffile")
    with tifffile.TiffWriter(path) as tw:
        for page in np.zeros((pages, 4, 4), np.uint8):
            if isinstance(compression, int):  # written as zlib, the code patched below
                tw.write(iter([encoded_zeros(compression)]), shape=(4, 4), dtype=np.uint8,
                         compression="zlib")
            else:
                tw.write(page, compression=compression)
    content = bytearray(path.read_bytes())
    assert patch_tags(content, 256, 4, "<I", side) == pages  # ImageWidth, LONG
    assert patch_tags(content, 257, 4, "<I", side) == pages  # ImageLength, LONG
    if isinstance(compression, int):
        assert patch_tags(content, 259, 3, "<H", compression) == pages  # Compression, SHORT
    path.write_bytes(bytes(content))


def patch_tags(content: bytearray, tag: int, kind: int, fmt: str, value: int) -> int:
    """Set every one-value `tag` entry of TIFF type `kind` in a little-endian TIFF's
    `content` to `value` (packed with `fmt`); how many were set."""
    entry, patched, i = struct.pack("<HHI", tag, kind, 1), 0, 0
    while (i := content.find(entry, i)) >= 0:
        packed = struct.pack(fmt, value)
        content[i + 8:i + 8 + len(packed)] = packed
        patched, i = patched + 1, i + 12
    return patched


def encoded_zeros(code: int) -> bytes:
    """16 zero bytes (a 4 x 4 uint8 page) encoded for TIFF Compression `code` without
    imagecodecs: LZW (5: ClearCode, 16 literal zeros, EndOfInformation, 9-bit codes),
    JPEG (6, 7: Pillow's baseline JPEG), LZMA (34925: xz), zstd (34926, 50000: one frame
    of one 4-byte RLE block); for any other code the 16 bytes as they are."""
    if code == 5:
        bits = "".join(f"{c:09b}" for c in [256, *[0] * 16, 257])
        bits += "0" * (-len(bits) % 8)
        return int(bits, 2).to_bytes(len(bits) // 8, "big")
    if code in (6, 7):
        from PIL import Image

        jpeg = io.BytesIO()
        Image.fromarray(np.zeros((4, 4), np.uint8)).save(jpeg, "JPEG")
        return jpeg.getvalue()
    if code == 34925:
        return lzma.compress(bytes(16))
    if code in (34926, 50000):
        rle_block = ((16 << 3) | (1 << 1) | 1).to_bytes(3, "little") + b"\0"  # last, RLE, 16
        return bytes.fromhex("28b52ffd") + bytes([0x20, 16]) + rle_block  # magic, size 16
    return bytes(16)


@pytest.mark.parametrize("compression", [None, "zlib"])
def test_tiff_whose_size_tags_lie_is_refused_before_decoding(tmp_path, monkeypatch,
                                                             compression):
    path = tmp_path / "lie.tif"
    lying_tiff(path, 30000, compression)
    monkeypatch.setattr(vio_common, "available_memory", lambda: 1 << 40)
    refused_cheaply(path, "TIFF shape (3, 30000, 30000) uint8 needs 2700000000 bytes",
                    "the file holds data for at most", "size tags are wrong")
    monkeypatch.setattr(vio_common, "available_memory", lambda: 1 << 30)
    refused_cheaply(path, "TIFF shape (3, 30000, 30000) uint8 needs 2.7 GB",
                    "memory available")


@pytest.mark.parametrize(("code", "bound"), [
    (5, 3 * 21 * 3641),  # LZW: 21 bytes a page, 8/9 of a 4096-byte code a byte
    (6, 3 * 4 * 4), (7, 3 * 4 * 4),  # JPEG: 4 x 4 x 1 samples in each page's frame header
    (34925, 3 * 68 * 273 * 376),  # LZMA: 376 decisions of 273 bytes a byte
    (34926, 3 * 10 * 32768), (50000, 3 * 10 * 32768)])  # zstd: 128 KiB per 4-byte block
def test_tiff_codecs_whose_size_tags_lie_are_refused_before_decoding(tmp_path, monkeypatch,
                                                                     code, bound):
    """LZW, JPEG, LZMA and zstd data are bounded by their format, so a lie is refused
    however much memory there is, before any is decoded (no imagecodecs needed)."""
    path = tmp_path / "lie.tif"
    lying_tiff(path, 30000, code)
    monkeypatch.setattr(vio_common, "available_memory", lambda: 1 << 40)
    refused_cheaply(path, "TIFF shape (3, 30000, 30000) uint8 needs 2700000000 bytes",
                    f"the file holds data for at most {bound}:", "size tags are wrong")


def test_tiff_codec_without_a_known_bound_reads_64_bytes_per_stored_byte(tmp_path,
                                                                          monkeypatch):
    """LERC (34887) has no bound here: a size past 64 bytes per stored byte is refused
    naming it; a smaller one is checked against memory only."""
    path = tmp_path / "lerc.tif"
    lying_tiff(path, 30000, 34887)
    monkeypatch.setattr(vio_common, "available_memory", lambda: 1 << 40)
    refused_cheaply(path, "TIFF shape (3, 30000, 30000) uint8 needs 2700000000 bytes",
                    "Compression 34887 has no known bound", f"{3 * 16 * 64} here",
                    "size tags are wrong")
    lying_tiff(path, 8, 34887)  # 192 bytes of samples, within 64 per stored byte
    monkeypatch.setattr(vio_common, "available_memory", lambda: 100)
    refused_cheaply(path, "TIFF shape (3, 8, 8) uint8 needs 1.92e-07 GB", "memory available")


@pytest.mark.parametrize("error", [ModuleNotFoundError("No module named 'compression'"),
                                   RuntimeError("ZstdError: ZSTD_decompress returned -20")])
@pytest.mark.parametrize("folder", [False, True])
def test_tiff_whose_codec_fails_is_refused_naming_it(tmp_path, monkeypatch, error, folder):
    """A codec's module missing, or its decoder rejecting the data, is refused naming the
    file, the codec's error and imagecodecs, for a stack and for a folder's slice."""
    tifffile = pytest.importorskip("tifffile")

    def failing_decoder(data, *args, **kwargs):
        raise error

    monkeypatch.setitem(tifffile.TIFF.DECOMPRESSORS._codecs, 50000, failing_decoder)
    path = tmp_path / "zstd.tif"
    lying_tiff(path, 4, 50000, pages=1)
    if folder:
        (tmp_path / "other.txt").write_text("not a slice")
        path = tmp_path
    load_error(path, "zstd.tif: TIFF ", "could not be decoded", str(error),
               "pip install imagecodecs", named=tmp_path / "zstd.tif")


@pytest.mark.parametrize("options", [
    {"compression": "lzma"},
    {"compression": "lzw"},
    {"compression": "zstd"},
    {"compression": "packbits"},
    {"compression": "jpeg", "compressionargs": {"lossless": True}},
    {"compression": "jpeg", "compressionargs": {"lossless": True}, "tile": (16, 16)}])
def test_tiff_stacks_of_each_codec_load_as_written(tmp_path, options):
    """Honest files pass the size check of their codec; all but LZMA need imagecodecs."""
    tifffile = pytest.importorskip("tifffile")
    if options["compression"] != "lzma":
        pytest.importorskip("imagecodecs")
    data = sample_data("uint8")
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, data, **options)
    np.testing.assert_array_equal(load_file(path).data, data)


@pytest.mark.parametrize("options", [{"truncate": True}, {"imagej": True, "truncate": True},
                                     {"compression": "zlib", "tile": (16, 16)}])
def test_tiff_stacks_whose_first_page_describes_the_data_load(tmp_path, options):
    """One IFD for a contiguous stack, tiles: the size check counts what tifffile reads."""
    tifffile = pytest.importorskip("tifffile")
    data = sample_data("uint16")
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, data, **options)
    np.testing.assert_array_equal(load_file(path).data, data)


def test_tiff_contiguous_stack_cut_short_is_refused(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    data = sample_data("uint16")
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, data, truncate=True)  # one IFD, then the samples
    with open(path, "r+b") as f:
        f.truncate(f.seek(0, 2) - 100)
    load_error(path, f"TIFF shape (5, 7, 11) uint16 needs {data.nbytes} bytes",
               "holds data for at most", "truncated")


def test_tiff_that_runs_out_of_memory_says_so_in_one_line(tmp_path, monkeypatch):
    tifffile = pytest.importorskip("tifffile")
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, sample_data("uint16"))

    def out_of_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(tifffile.TiffPageSeries, "asarray", out_of_memory)
    load_error(path, "TIFF shape (5, 7, 11) uint16", "not enough memory")


def test_tiff_folder_slices_whose_size_tags_lie(tmp_path, monkeypatch):
    tifffile = pytest.importorskip("tifffile")
    folder = tmp_path / "slices"
    folder.mkdir()
    tifffile.imwrite(folder / "s1.tif", np.zeros((4, 4), np.uint8))
    lying_tiff(folder / "s2.tif", 30000, pages=1)
    with pytest.raises(VolumeError, match=re.escape(f"{folder / 's2.tif'}: slice shape "
                                                    "(30000, 30000) differs")):
        load_file(folder)
    (folder / "s1.tif").unlink()
    monkeypatch.setattr(vio_common, "available_memory", lambda: 1 << 40)
    with pytest.raises(VolumeError, match=re.escape(str(folder / "s2.tif"))) as info:
        load_file(folder)
    assert "the file holds data for at most 16" in str(info.value)
    monkeypatch.setattr(vio_common, "available_memory", lambda: 1 << 30)
    with pytest.raises(VolumeError, match=r"needs 1\.8 GB of samples"):
        load_file(folder)


# --------------------------------------------------------------------------- folders, DICOM


def test_folder_with_neither_dicom_nor_tiff(tmp_path):
    folder = tmp_path / "stuff"
    folder.mkdir()
    (folder / "readme.txt").write_text("hello")
    load_error(folder, "neither DICOM", "TIFF", "readme.txt")
    empty = tmp_path / "empty"
    empty.mkdir()
    load_error(empty, "neither DICOM", "0 file(s)")


def test_dicom_folder_without_pydicom(tmp_path, monkeypatch):
    folder = tmp_path / "series"
    folder.mkdir()
    (folder / "IM0001.dcm").write_bytes(bytes(128) + b"DICM" + bytes(64))
    monkeypatch.setitem(sys.modules, "pydicom", None)
    load_error(folder, 'needs pydicom: pip install "isolume[dicom]"')


CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


def write_dicom_series(
    folder: Path,
    data: np.ndarray,
    *,
    prefix: str = "IM",
    with_positions: bool = True,
    slope: float = 2.0,
    intercept: float = -100.0,
    seed: int = 0,
) -> None:
    """One CT file per z slice, written in shuffled order, raw int16 pixels."""
    pytest.importorskip("pydicom")
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    series_uid, study_uid = generate_uid(), generate_uid()
    depth = data.shape[0]
    order = np.random.default_rng(seed).permutation(depth)
    for n, k in enumerate(order):
        uid = generate_uid()
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
        meta.MediaStorageSOPInstanceUID = uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        path = folder / f"{prefix}{n:03d}"
        ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID = CT_IMAGE_STORAGE
        ds.SOPInstanceUID = uid
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.Modality = "CT"
        ds.Rows, ds.Columns = data.shape[1], data.shape[2]
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
        ds.PixelRepresentation = 1
        ds.PixelSpacing = [SPACING[1], SPACING[0]]  # row spacing (y), column spacing (x)
        ds.RescaleSlope = slope
        ds.RescaleIntercept = intercept
        if with_positions:
            ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
            ds.ImagePositionPatient = [ORIGIN[0], ORIGIN[1], ORIGIN[2] + int(k) * SPACING[2]]
            ds.InstanceNumber = depth - int(k)  # reversed on purpose: positions must win
        else:
            ds.InstanceNumber = int(k) + 1
            ds.SliceThickness = SPACING[2]
        ds.PixelData = data[k].astype("<i2").tobytes()
        ds.save_as(path, enforce_file_format=True)


def test_dicom_series_round_trip(tmp_path):
    data = sample_data("int16")
    folder = tmp_path / "series"
    folder.mkdir()
    write_dicom_series(folder, data)
    write_dicom_series(folder, data[:2], prefix="SCOUT", seed=1)  # smaller series: ignored
    (folder / "notes.txt").write_text("not DICOM")
    vol = load_file(folder)
    assert_volume(vol, data * 2.0 - 100.0, name="series")


def test_dicom_folder_beside_tiff_names_that_are_no_slices_is_placed_as_dicom(tmp_path):
    """A hidden file or a folder named *.tif is no TIFF slice to the folder loader, nor to
    the placement's label."""
    data = sample_data("int16")
    folder = tmp_path / "series"
    folder.mkdir()
    write_dicom_series(folder, data)
    (folder / "._IM000.tif").write_bytes(b"macOS resource fork")
    (folder / "thumbs.tif").mkdir()
    vol = load_file(folder)
    assert_volume(vol, data * 2.0 - 100.0, name="series")
    assert "DICOM orientation" in vol.placement and "TIFF" not in vol.placement


def test_dicom_series_instance_number_fallback(tmp_path):
    data = sample_data("int16")
    folder = tmp_path / "series"
    folder.mkdir()
    write_dicom_series(folder, data, with_positions=False, slope=1.0, intercept=0.0)
    assert_volume(load_file(folder, origin=ORIGIN), data)


def test_dicom_missing_slice(tmp_path):
    folder = tmp_path / "series"
    folder.mkdir()
    write_dicom_series(folder, sample_data("int16"))
    files = sorted(folder.iterdir())
    import pydicom

    middle = next(f for f in files if pydicom.dcmread(f).ImagePositionPatient[2] == ORIGIN[2] + 4)
    middle.unlink()
    load_error(folder, "not evenly spaced")


# --------------------------------------------------------------------------- shared data


@pytest.mark.shared
@pytest.mark.skipif(not CTHEAD.exists(), reason=f"{CTHEAD} not present (../shared is optional)")
def test_shared_cthead():
    vol = load_file(CTHEAD)
    assert vol.data.shape == (113, 256, 256)
    assert vol.value_range == (0.0, 3272.0)
    assert vol.name == "CThead"


def test_raw_spacing_from_a_manifest_beside_the_file(tmp_path):
    """Open SciVis-style collections keep voxel sizes in manifest.json next to the files."""
    import json

    data = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4)
    raw = tmp_path / "part_4x3x2_uint8.raw"
    data.tofile(raw)
    assert load_file(raw).spacing == (1.0, 1.0, 1.0)
    record = {"file": raw.name, "spacing_xyz": [0.5, 0.5, 2.0]}
    (tmp_path / "manifest.json").write_text(json.dumps([{"file": "other.raw"}, record]))
    assert load_file(raw).spacing == (0.5, 0.5, 2.0)
    assert load_file(raw, spacing=(1, 2, 3)).spacing == (1.0, 2.0, 3.0)  # explicit wins
    (tmp_path / "manifest.json").write_text("{not json")
    assert load_file(raw).spacing == (1.0, 1.0, 1.0)


# --------------------------------------------------------------------------- orientation
# Each format writes the asymmetric volume with index axes permuted and flipped in the
# world; loaded, every sample must sit at the world position (LPS) the header gives it.
AXES = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Columns: world direction of index axes x, y, z (x → −y, y → +z, z → −x)."""


def assert_placed(vol, data, world_of) -> None:
    """Every sample of (Z, Y, X) `data` is found in `vol` at `world_of(i, j, k)` (LPS)."""
    k, j, i = (a.reshape(-1) for a in np.indices(data.shape))
    points = world_of(np.stack([i, j, k], axis=1).astype(np.float64))
    index = np.rint(vol.world_to_index(points)).astype(int)
    np.testing.assert_allclose(vol.world_to_index(points), index, atol=1e-6)
    np.testing.assert_array_equal(vol.data[index[:, 0], index[:, 1], index[:, 2]],
                                  data.reshape(-1).astype(np.float32))
    assert (np.asarray(vol.spacing) > 0).all()


def oriented(origin, directions):
    """World position of index (i, j, k) rows: origin + directions @ (spacing * index)."""
    return lambda ijk: np.asarray(origin) + (ijk * np.asarray(SPACING)) @ np.asarray(
        directions).T


def test_nrrd_orientation_in_ras_is_placed_in_lps(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    data = sample_data("int16")
    path = tmp_path / "oriented.nrrd"
    header = {"space": "right-anterior-superior",
              "space directions": (AXES * np.asarray(SPACING)).T,  # one row per axis
              "space origin": np.array(ORIGIN)}
    nrrd.write(str(path), data, header, index_order="C")
    ras_to_lps = np.array([-1.0, -1.0, 1.0])
    vol = load_file(path)
    assert_placed(vol, data, lambda ijk: ras_to_lps * oriented(ORIGIN, AXES)(ijk))
    # RAS x → −y, y → +z, z → −x is LPS x → +y, y → +z, z → +x
    assert vol.placement == "NRRD orientation, in LPS: index axes x, y, z along world +y, +z, +x"
    raw = tmp_path / "vol_11x7x5_int16.raw"
    raw.write_bytes(data.astype("<i2").tobytes())
    assert "gives no orientation (--up AXIS turns it)" in load_file(raw).placement


def test_nifti_affine_is_placed_in_lps(tmp_path):
    nib = pytest.importorskip("nibabel")
    data = sample_data("int16")
    affine = np.eye(4)
    affine[:3, :3] = AXES * np.asarray(SPACING)
    affine[:3, 3] = ORIGIN
    path = tmp_path / "oriented.nii.gz"
    nib.save(nib.Nifti1Image(data.transpose(2, 1, 0), affine), str(path))
    ras_to_lps = np.array([-1.0, -1.0, 1.0])
    assert_placed(load_file(path), data,
                  lambda ijk: ras_to_lps * oriented(ORIGIN, AXES)(ijk))


def test_metaimage_transform_matrix_is_applied(tmp_path):
    data = sample_data("int16")
    path = tmp_path / "oriented.mha"
    write_metaimage(path, data)
    matrix = " ".join(f"{v:g}" for v in AXES.T.reshape(-1))  # one axis per three numbers
    text = path.read_bytes().replace(b"NDims = 3\n", f"NDims = 3\nTransformMatrix = "
                                     f"{matrix}\n".encode())
    path.write_bytes(text)
    assert_placed(load_file(path), data, oriented(ORIGIN, AXES))
    path.write_bytes(text.replace(f"TransformMatrix = {matrix}".encode(),
                                  b"TransformMatrix = 1 0 0 1"))
    load_error(path, "TransformMatrix", "9 number(s)")


def test_dicom_orientation_is_applied(tmp_path):
    """A sagittal series: rows run along +y (posterior), columns down −z, slices along
    row × column = −x."""
    data = sample_data("int16")
    folder = tmp_path / "sagittal"
    folder.mkdir()
    write_dicom_series(folder, data, slope=1.0, intercept=0.0)
    import pydicom

    row, col = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0])
    normal = np.cross(row, col)
    for file in folder.iterdir():
        ds = pydicom.dcmread(file)
        k = round((float(ds.ImagePositionPatient[2]) - ORIGIN[2]) / SPACING[2])
        ds.ImageOrientationPatient = [*row, *col]
        ds.ImagePositionPatient = list(np.asarray(ORIGIN) + k * SPACING[2] * normal)
        ds.save_as(file)
    directions = np.stack([row, col, normal], axis=1)
    assert_placed(load_file(folder), data, oriented(ORIGIN, directions))


def test_orientation_can_be_left_out(tmp_path):
    data = sample_data("int16")
    path = tmp_path / "oriented.mha"
    write_metaimage(path, data)
    path.write_bytes(path.read_bytes().replace(
        b"NDims = 3\n", b"NDims = 3\nTransformMatrix = 0 -1 0 0 0 1 -1 0 0\n"))
    assert_volume(load_file(path, orientation=False), data)


def test_a_lattice_file_given_as_a_volume_says_what_it_is(tmp_path):
    """An .npz of a lattice's members is named as a lattice, to give with --lattice."""
    path = tmp_path / "l.npz"
    np.savez(path, values=np.zeros((1, 3), np.float32), samples=np.ones(1, np.uint32),
             held=np.ones(1, np.uint8), meta=np.array("{}"))
    load_error(path, "an illumination lattice", "give it with --lattice")


@pytest.mark.parametrize(("cut", "fragment"), [
    (lambda data: data[:40], "its gzip data are damaged or cut short"),
    (lambda data: b"not gzip" * 100, "its gzip data are damaged or cut short"),
    (lambda data: gzip.compress(gzip.decompress(data)[:100]), "its gzip data end after 100 "
                                                               "bytes, before the 348")])
def test_a_nifti_gz_without_a_header_says_its_gzip_data_are_short(tmp_path, cut, fragment):
    """A .nii.gz whose gzip data give no header names that, not nibabel's guess about
    the file's type."""
    nib = pytest.importorskip("nibabel")
    whole = tmp_path / "whole.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros((4, 4, 4), np.float32), np.eye(4)), str(whole))
    path = tmp_path / "cut.nii.gz"
    path.write_bytes(cut(whole.read_bytes()))
    load_error(path, "not a readable NIfTI file", fragment)
