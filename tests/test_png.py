"""`app.render.png`: PNG files deflated in bands on every core, read back by Pillow."""

from __future__ import annotations

import io
import zlib

import numpy as np
import pytest
from PIL import Image

from isolume.app.render import png
from isolume.volumes import cores


def _read(data: bytes) -> Image.Image:
    """The picture of a PNG file, decoded by Pillow (which checks every chunk's CRC, and
    zlib the stream's Adler-32)."""
    picture = Image.open(io.BytesIO(data))
    picture.load()
    return picture


def _shaded(height: int, width: int) -> np.ndarray:
    """(H, W, 3) uint8: a Lambert-shaded sphere on a dark ground with a little noise, as
    renders look (smooth rows, a sharp outline)."""
    y, x = np.mgrid[-1:1:height * 1j, -1:1:width * 1j]
    r2 = x * x + y * y
    nz = np.sqrt(np.clip(1 - r2 / 0.64, 0, 1))
    light = np.where(r2 < 0.64, 0.2 + 0.8 * np.clip(0.3 * x + 0.4 * y + 0.87 * nz, 0, 1), 0.1)
    noise = np.random.default_rng(1).normal(0, 0.01, (height, width, 1))
    colour = np.array([0.9, 0.7, 0.5]) * (light[..., None] + noise)
    return np.clip(255 * colour, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("shape", [(1, 1), (7, 5), (1, 1024), (1024, 1), (300, 257),
                                   (900, 300), (5, 90_000)])
def test_pictures_read_back_exactly_with_their_text(shape):
    """Any size (one pixel, one row, one column, rows of odd byte counts, several bands,
    rows longer than a band and than the window that primes the next) reads back as
    written, with Latin-1 text as ``tEXt`` and other text as ``iTXt``."""
    picture = np.random.default_rng(shape[0]).integers(0, 256, (*shape, 3), dtype=np.uint8)
    text = {"isolume": "lit, ρ = 0.5", "Software": "isolume héllo"}
    data = png.encode_png(picture, text)
    back = _read(data)
    assert back.mode == "RGB" and np.array_equal(np.asarray(back), picture)
    assert back.text == text
    assert (b"iTXtisolume" in data) and (b"tEXtSoftware" in data)


def test_the_file_is_the_same_for_any_thread_count_and_cut_into_bands():
    """The bands depend on the picture alone: 1 and 3 threads write the same bytes, and a
    1024 × 768 picture is deflated in several bands that join into one zlib stream."""
    picture = _shaded(768, 1024)
    bands = png.band_rows(768, 1024 * 3 + 1)
    assert len(bands) == 10 and bands[0] == (0, 85) and bands[-1][1] == 768
    try:
        files = []
        for threads in (1, 3):
            cores.use(threads)
            files.append(png.encode_png(picture))
    finally:
        cores.use(None)
    assert files[0] == files[1]
    assert np.array_equal(np.asarray(_read(files[0])), picture)


def test_a_long_stream_is_cut_into_several_idat_chunks(monkeypatch):
    """The zlib stream goes into IDAT chunks of at most `IDAT_BYTES` (PNG's chunks hold
    less than 2³¹ bytes), which a reader joins."""
    monkeypatch.setattr(png, "IDAT_BYTES", 1000)
    picture = np.random.default_rng(7).integers(0, 256, (60, 50, 3), dtype=np.uint8)
    data = png.encode_png(picture)
    kinds, sizes, at = [], [], len(png.SIGNATURE)
    while at < len(data):  # the file's chunks: length, type, data, CRC
        length = int.from_bytes(data[at:at + 4], "big")
        kinds.append(data[at + 4:at + 8])
        sizes.append(length)
        at += 12 + length
    idat = [size for kind, size in zip(kinds, sizes, strict=True) if kind == b"IDAT"]
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND" and len(idat) >= 8
    assert set(idat[:-1]) == {1000} and 0 < idat[-1] <= 1000
    assert np.array_equal(np.asarray(_read(data)), picture)


def test_the_up_filter_and_the_stream_are_png_s():
    """The IDAT data is one zlib stream whose bytes are each row's filter byte (2, Up)
    and the row less the row above, modulo 256 (the first row less zeros)."""
    picture = np.random.default_rng(3).integers(0, 256, (40, 9, 3), dtype=np.uint8)
    data = png.encode_png(picture)
    at = data.index(b"IDAT")
    length = int.from_bytes(data[at - 4:at], "big")
    rows = np.frombuffer(zlib.decompress(data[at + 4:at + 4 + length]), np.uint8)
    rows = rows.reshape(40, 28)
    assert (rows[:, 0] == 2).all()
    flat = picture.reshape(40, 27).astype(np.int16)
    expected = np.vstack([flat[:1], flat[1:] - flat[:-1]]) % 256
    assert np.array_equal(rows[:, 1:], expected)


def test_a_rendered_picture_is_no_larger_than_pillow_makes_it():
    """On a picture as renders look, the file is within 5 % of Pillow's (level 6 both;
    the Up filter against Pillow's own choice)."""
    picture = _shaded(512, 640)
    ours = len(png.encode_png(picture))
    buffer = io.BytesIO()
    Image.fromarray(picture).save(buffer, format="PNG")
    assert ours <= 1.05 * len(buffer.getvalue())


def test_bands_adler_32_combine_as_zlib_s_of_the_joined_bytes():
    """`adler32_combine` of two strings' Adler-32 is that of the strings joined: empty
    ones, one byte, lengths past the modulus (65521), bytes of 255."""
    rng = np.random.default_rng(5)
    for first_length, second_length in [(0, 0), (0, 5), (5, 0), (1, 1), (70_000, 131_042),
                                        (65_521, 65_521), (3, 200_000)]:
        first = rng.integers(0, 256, first_length, dtype=np.uint8).tobytes()
        second = bytes([255]) * second_length if first_length == 3 else \
            rng.integers(0, 256, second_length, dtype=np.uint8).tobytes()
        joined = png.adler32_combine(zlib.adler32(first), zlib.adler32(second),
                                     len(second))
        assert joined == zlib.adler32(first + second)


def test_a_band_is_primed_with_the_window_before_it():
    """Rows that step by the same random bytes (under the Up filter: one random row again
    and again, 30 001 bytes, 8 rows a band) deflate to about four rows (matches of 258
    bytes): each band's first row matches the band before's last, which primes its
    deflate (what a reader's window holds there); unprimed, each of the 50 bands would
    hold a row of literals. The file reads back."""
    step = np.random.default_rng(9).integers(0, 256, (1, 10_000, 3), dtype=np.uint8)
    picture = (np.arange(400, dtype=np.uint8)[:, None, None] * step).astype(np.uint8)
    assert len(png.band_rows(400, 30_001)) == 50
    data = png.encode_png(picture)
    assert len(data) < 5 * 30_001  # 0.12 MB; unprimed 1.6 MB
    assert np.array_equal(np.asarray(_read(data)), picture)


def test_bad_pictures_and_keywords_are_refused():
    for wrong in (np.zeros((4, 4, 3), np.uint16), np.zeros((4, 4, 3)), [[[0, 0, 0]]]):
        with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8, got"):
            png.encode_png(wrong)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) with H, W ≥ 1, got \(4, 4\)"):
        png.encode_png(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"\(0, 4, 3\)"):
        png.encode_png(np.zeros((0, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="keyword 'ρ'"):
        png.encode_png(np.zeros((2, 2, 3), np.uint8), {"ρ": "x"})
