"""PNG files deflated on every core: an 8-bit RGB picture, its rows under PNG's "Up" filter
(each row less the row above, byte by byte), cut into bands of `BAND_BYTES` that the
pool's threads filter and deflate each on its own — primed with the last 32 KiB of the
band before (a dictionary: the window a reader of the joined stream holds there) and
ended by a sync flush, so that the bands join into one zlib stream (as ``pigz`` cuts a
file) — each with its Adler-32, combined in order. Pillow's encoder deflates on one
thread (a 1024² render: 0.13 s of one core; a 4K frame 0.4–0.5 s). The bands are fixed
by the picture's size alone, so the file is the same byte for byte whatever the number
of threads; its size is within a few per cent of Pillow's (the Up filter suits rendered
pictures, whose rows change little)."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator

import numpy as np

from isolume.volumes import cores

BAND_BYTES = 1 << 18
"""Filtered bytes (whole rows, at least one) a band holds: a 1024² picture makes 13 bands,
a 3840 × 2160 one 99."""
WINDOW = 1 << 15
"""Bytes of the band before that prime a band's deflate (deflate's window: the most a
match reaches back)."""
LEVEL = 6
"""zlib's compression level (Pillow's and zlib's default)."""
IDAT_BYTES = 1 << 30
"""Most bytes of the zlib stream one IDAT chunk holds (PNG allows 2³¹ − 1 a chunk)."""
SIGNATURE = b"\x89PNG\r\n\x1a\n"
_UP = 2  # PNG filter type: each byte less the byte above it
_ADLER_BASE = 65521


def encode_png(srgb: np.ndarray, text: dict[str, str] | None = None) -> bytes:
    """The PNG file of an (H, W, 3) uint8 sRGB picture, with `text` (keyword → value)
    as text chunks: ``tEXt`` where the value is Latin-1, else ``iTXt`` (UTF-8).

    Raises:
        ValueError: a picture that is not (H, W, 3) uint8 with H, W ≥ 1, or a keyword
            that PNG does not allow (1–79 Latin-1 characters).
    """
    return b"".join(_pieces(srgb, text))


def write_png(path: str | os.PathLike[str], srgb: np.ndarray,
              text: dict[str, str] | None = None) -> None:
    """Write an (H, W, 3) uint8 sRGB picture to `path` as PNG (`encode_png`), its chunks
    written as they are, not joined first."""
    pieces = _pieces(srgb, text)
    with open(path, "wb") as out:
        for piece in pieces:
            out.write(piece)


def band_rows(height: int, row_bytes: int) -> list[tuple[int, int]]:
    """(first, end) rows of each band of a picture of `height` rows of `row_bytes` filtered
    bytes (the filter byte included): `BAND_BYTES` worth of whole rows each, the last
    band what is left."""
    rows = max(1, BAND_BYTES // row_bytes)
    return [(lo, min(lo + rows, height)) for lo in range(0, height, rows)]


def adler32_combine(first: int, second: int, second_length: int) -> int:
    """The Adler-32 of two byte strings joined, from each one's (`first`, `second`) and
    the second's length (zlib's ``adler32_combine``, which Python's zlib lacks)."""
    ones = ((first & 0xFFFF) + (second & 0xFFFF) - 1) % _ADLER_BASE
    sums = ((first >> 16) + (second >> 16)
            + second_length * ((first & 0xFFFF) - 1)) % _ADLER_BASE
    return ones | sums << 16


def _pieces(srgb: np.ndarray, text: dict[str, str] | None) -> Iterator[bytes | memoryview]:
    """The PNG file of `encode_png`, in pieces: the signature, the chunks' parts. The
    picture and the text are checked before the first piece."""
    if not isinstance(srgb, np.ndarray) or srgb.dtype != np.uint8:
        kind = srgb.dtype if isinstance(srgb, np.ndarray) else type(srgb).__name__
        raise ValueError(f"a PNG picture is (H, W, 3) uint8, got {kind}")
    pixels = np.ascontiguousarray(srgb)
    if pixels.ndim != 3 or pixels.shape[2] != 3 or 0 in pixels.shape:
        raise ValueError(f"a PNG picture is (H, W, 3) with H, W ≥ 1, got {pixels.shape}")
    height, width, _ = pixels.shape
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit RGB
    texts = [_text_chunk(key, value) for key, value in (text or {}).items()]
    stream = memoryview(_deflated_rows(pixels.reshape(height, width * 3)))
    return _joined(header, texts, stream)


def _joined(header: bytes, texts: list[bytes], stream: memoryview
            ) -> Iterator[bytes | memoryview]:
    """The file's pieces: signature, IHDR of `header`, the `texts` chunks, the zlib
    `stream` in IDAT chunks of at most `IDAT_BYTES`, IEND."""
    yield SIGNATURE
    yield _chunk(b"IHDR", header)
    yield from texts
    for lo in range(0, len(stream), IDAT_BYTES):
        yield from _chunk_parts(b"IDAT", stream[lo:lo + IDAT_BYTES])
    yield _chunk(b"IEND", b"")


def _deflated_rows(rows: np.ndarray) -> bytes:
    """The zlib stream of (H, R) uint8 rows under the Up filter: the bands filtered and
    deflated on the pool (`_band`), joined, with zlib's header and the Adler-32 of the
    filtered bytes (the bands' own, combined)."""
    bands = band_rows(len(rows), rows.shape[1] + 1)
    out: list[tuple[bytes, int, int]] = [(b"", 1, 0)] * len(bands)

    def band(i: int) -> None:
        lo, hi = bands[i]
        out[i] = _band(rows, lo, hi, last=i == len(bands) - 1)

    cores.for_items(band, len(bands), "png")
    adler = 1
    for _, band_adler, length in out:
        adler = adler32_combine(adler, band_adler, length)
    return b"\x78\x9c" + b"".join(deflated for deflated, _, _ in out) \
        + struct.pack(">I", adler)


def _band(rows: np.ndarray, lo: int, hi: int, last: bool) -> tuple[bytes, int, int]:
    """(raw deflate, Adler-32, length) of the filtered rows `lo` … `hi` − 1 of `rows`
    (H, R) uint8 (`_filtered`), deflated with the last `WINDOW` filtered bytes before
    them as the dictionary and ended by a sync flush (byte-aligned, not final), or by the
    final block where it is the `last` band."""
    data = _filtered(rows, lo, hi).tobytes()
    before = max(0, lo - -(-WINDOW // (rows.shape[1] + 1)))
    primed = {"zdict": _filtered(rows, before, lo).tobytes()[-WINDOW:]} if lo else {}
    deflate = zlib.compressobj(LEVEL, zlib.DEFLATED, -15, **primed)
    end = zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH
    return deflate.compress(data) + deflate.flush(end), zlib.adler32(data), len(data)


def _filtered(rows: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Rows `lo` … `hi` − 1 of `rows` (H, R) uint8 under the Up filter, (hi − lo, R + 1):
    each led by its filter byte and less the row above (the picture's first row less
    zeros), modulo 256 as PNG's."""
    filtered = np.empty((hi - lo, rows.shape[1] + 1), np.uint8)
    filtered[:, 0] = _UP
    filtered[:, 1:] = rows[lo:hi]
    start = max(lo, 1)  # the picture's first row keeps its bytes: the row above is zeros
    np.subtract(rows[start:hi], rows[start - 1:hi - 1], out=filtered[start - lo:, 1:])
    return filtered


def _chunk(kind: bytes, data: bytes | memoryview) -> bytes:
    """A PNG chunk: length, type, data, CRC-32 of the type and data."""
    return b"".join(_chunk_parts(kind, data))


def _chunk_parts(kind: bytes, data: bytes | memoryview) -> tuple[bytes, bytes | memoryview,
                                                                  bytes]:
    """A PNG chunk in three parts, `data` not copied: its length and type, `data`, the
    CRC-32 of the type and data."""
    return (struct.pack(">I", len(data)) + kind, data,
            struct.pack(">I", zlib.crc32(data, zlib.crc32(kind))))


def _text_chunk(key: str, value: str) -> bytes:
    """A ``tEXt`` chunk of `key` and a Latin-1 `value`, else an uncompressed ``iTXt`` one."""
    try:
        keyword = key.encode("latin-1")
    except UnicodeEncodeError:
        keyword = b""
    if not 1 <= len(keyword) <= 79 or b"\0" in keyword:
        raise ValueError(f"PNG text keyword {key!r}: expected 1–79 Latin-1 characters")
    try:
        return _chunk(b"tEXt", keyword + b"\0" + value.encode("latin-1"))
    except UnicodeEncodeError:
        return _chunk(b"iTXt", keyword + b"\0\0\0\0\0" + value.encode("utf-8"))
