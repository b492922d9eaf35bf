"""Files that lie about their size: decompression bombs and headers promising more than
the machine holds are refused in one line, having cost no more memory than the samples
they promised (measured with tracemalloc, which sees numpy's and zlib's allocations)."""

from __future__ import annotations

import gzip
import re
import tracemalloc
import zlib

import numpy as np
import pytest

from isolume.volumes.core import VolumeError
from isolume.volumes.io import load_file

BOMB = 64 << 20
"""Bytes a bomb inflates to: 64 MiB of zeros, 64 KiB compressed."""
PROMISED = 16 * 16 * 16
"""Bytes of samples the bombs' names and headers promise (16³ uint8)."""


def _refused_cheaply(path, *fragments) -> str:
    """Load `path`: a one-line VolumeError naming it and `fragments`, the peak of traced
    memory below 8 MiB (an eighth of the bomb)."""
    tracemalloc.start()
    try:
        with pytest.raises(VolumeError, match=re.escape(str(path))) as info:
            load_file(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    assert peak < BOMB // 8, f"peak {peak / 2**20:.1f} MiB"
    return message


def _bomb_bytes() -> bytes:
    return bytes(BOMB)


def test_a_raw_gz_bomb_stops_one_byte_past_its_name(tmp_path):
    path = tmp_path / "bomb_16x16x16_uint8.raw.gz"
    path.write_bytes(gzip.compress(_bomb_bytes()))
    _refused_cheaply(path, "4096 bytes", "more decompressed bytes")


def test_a_raw_file_named_bigger_than_memory_is_refused_before_reading(tmp_path):
    path = tmp_path / "huge_100000x100000x100000_uint8.raw.gz"
    path.write_bytes(gzip.compress(bytes(PROMISED)))
    _refused_cheaply(path, "1e+06 GB", "memory available", "--crop X0:X1,Y0:Y1,Z0:Z1")


def test_an_uncompressed_raw_file_of_the_wrong_size_is_refused_unread(tmp_path):
    path = tmp_path / "big_100000x100000x100000_uint8.raw"
    path.write_bytes(bytes(PROMISED))
    _refused_cheaply(path, "got only 4096 bytes", "truncated")


def _nrrd_header(sizes: str, encoding: str) -> bytes:
    return (f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {sizes}\nencoding: {encoding}\n"
            "\n").encode()


def test_a_gzip_nrrd_bomb_stops_one_byte_past_its_header(tmp_path):
    pytest.importorskip("nrrd")
    path = tmp_path / "bomb.nrrd"
    path.write_bytes(_nrrd_header("16 16 16", "gzip") + gzip.compress(_bomb_bytes()))
    _refused_cheaply(path, "expected 4096 decompressed bytes", "holds more")


def test_an_nrrd_header_bigger_than_memory_is_refused_before_reading(tmp_path):
    pytest.importorskip("nrrd")
    path = tmp_path / "huge.nrrd"
    path.write_bytes(_nrrd_header("100000 100000 100000", "raw") + bytes(PROMISED))
    _refused_cheaply(path, "sizes 100000 100000 100000", "memory available")


def test_bounded_nrrd_reading_gives_pynrrds_samples(tmp_path):
    """Attached raw and gzip data, little- and big-endian, as pynrrd reads them."""
    nrrd = pytest.importorskip("nrrd")
    rng = np.random.default_rng(4)
    data = rng.integers(0, 60000, (5, 6, 7)).astype(np.uint16)
    for encoding in ("raw", "gzip"):
        for endian in ("little", "big"):
            path = tmp_path / f"v_{encoding}_{endian}.nrrd"
            nrrd.write(str(path), data, {"encoding": encoding, "endian": endian},
                       index_order="C")
            volume = load_file(path)
            np.testing.assert_array_equal(np.asarray(volume.data), data.astype(np.float32))


def test_a_compressed_metaimage_bomb_stops_one_byte_past_its_header(tmp_path):
    path = tmp_path / "bomb.mha"
    header = (b"ObjectType = Image\nNDims = 3\nDimSize = 16 16 16\nElementType = MET_UCHAR\n"
              b"CompressedData = True\nElementDataFile = LOCAL\n")
    path.write_bytes(header + zlib.compress(_bomb_bytes()))
    _refused_cheaply(path, "expected 16*16*16*1 = 4096 bytes", "got 4097 bytes")
