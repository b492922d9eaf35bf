"""TIFF volumes via tifffile (extra ``tiff``): a multi-page stack (page = z) or a folder
of 2-D slices sorted naturally by name."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np

from isolume.volumes.core import VolumeError
from isolume.volumes.io.common import (
    READ_ERRORS,
    Loaded,
    check_fits_in_memory,
    check_readable,
    one_line,
    optional_module,
)

TIFF_SUFFIXES = (".tif", ".tiff")


def load_tiff_file(path: Path) -> Loaded:
    """Multi-page TIFF (page = z slice) -> (Z, Y, X); ImageJ metadata give the spacing.

    The samples' size (the tags' shape × type) is checked against memory, and against
    what the file's stored bytes can decode to (`_check_size`), before any is decoded.
    """
    tifffile = optional_module("tifffile", path)
    what = "the image"
    try:
        with tifffile.TiffFile(str(path)) as tif:
            series, size = tif.series[0], tif.filehandle.size
            what = f"shape {tuple(series.shape)} {series.dtype}"
            _check_size(series, int(series.nbytes), 1, str(path), size, what)
            arr = np.asarray(series.asarray())
            if arr.ndim == 2 and len(tif.pages) > 1:
                arr = _stacked_pages(tif.pages, str(path), size)
            spacing = _imagej_spacing(tif)
    except VolumeError:
        raise
    except MemoryError:
        raise VolumeError(f"{path}: TIFF {what}: not enough memory to decode it; load a "
                          "smaller stack") from None
    except _CODEC_ERRORS as exc:
        raise _undecodable(str(path), what, exc) from None
    except (tifffile.TiffFileError, *READ_ERRORS) as exc:
        raise VolumeError(f"{path}: not a readable TIFF file: {one_line(exc)}") from None
    if arr.ndim > 3:
        arr = arr.reshape([s for s in arr.shape if s != 1] or [1])
    if arr.ndim != 3:
        raise VolumeError(
            f"{path}: expected a grey-scale TIFF stack (one page per z slice), got an "
            f"array of shape {arr.shape}"
        )
    return arr, spacing, None, None


_CODEC_ERRORS = (ImportError, RuntimeError)
"""What decoding a page raises where its codec's module is missing (tifffile imports
some codecs only when a page needs them) or where imagecodecs' decoder rejects the data
(its errors derive from RuntimeError)."""


def _undecodable(where: str, what: str, exc: BaseException) -> VolumeError:
    """The refusal of TIFF data that tifffile could not decode (`_CODEC_ERRORS`)."""
    return VolumeError(f"{where}: TIFF {what}: its compressed data could not be decoded "
                       f"({one_line(exc)}); expected data its codec reads, with the "
                       "imagecodecs package installed (pip install imagecodecs) for codecs "
                       "other than Deflate, PackBits and LZMA")


def _stacked_pages(pages: Any, where: str, size: int) -> np.ndarray:
    """(Z, Y, X) stack of the 2-D pages of a file whose first series is one page, their
    sizes checked first (`_check_size`: the pages and their stack)."""
    nbytes = sum(int(page.nbytes) for page in pages)
    _check_size(pages, nbytes, 2, where, size, f"{len(pages)} pages")
    arrays = [np.asarray(page.asarray()) for page in pages]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise VolumeError(f"{where}: TIFF pages differ in shape {sorted(shapes)}; expected "
                          "one (Y, X) shape for every z slice")
    return np.stack(arrays)


_LZW_EXPANSION = 4096 * 8 // 9 + 1
"""Most bytes one stored byte of TIFF LZW decodes to: its codes are 9 to 12 bits long, so
a byte holds at most 8/9 of a code, and a code emits one of the 4096 table entries'
strings, at most 4096 bytes (each entry is at most one byte longer than an earlier one)."""

_ZSTD_EXPANSION = (128 << 10) // 4
"""Most bytes one stored byte of zstd decodes to: every block decodes to at most
Block_Maximum_Size, 128 KiB (RFC 8878, 3.1.1.2), and the smallest block that reaches it
is an RLE block of 4 bytes (its 3-byte header and the byte repeated); a frame's header
and the other block types only add stored bytes."""

_LZMA_EXPANSION = 273 * 376
"""Most bytes one stored byte of LZMA (xz, LZMA2) decodes to: every literal or match,
1 to 273 bytes, starts with an adaptive range-coder decision, whose probability (in
1/2048) stays within 31..2017, so each decision shrinks the 32-bit range by a factor
above 2048/2018, i.e. consumes more than log2(2048/2018) > 8/376 bits, and one stored
byte is read per 8 bits consumed: fewer than 376 decisions per stored byte. LZMA2's
uncompressed chunks and xz's filters decode 1:1."""

_MAX_EXPANSION = {1: 1, 5: _LZW_EXPANSION, 8: 1032, 32946: 1032, 32773: 128,
                  34925: _LZMA_EXPANSION, 34926: _ZSTD_EXPANSION, 50000: _ZSTD_EXPANSION}
"""TIFF Compression code -> the most bytes one stored byte decodes to: none (1), LZW (5),
Deflate (8, 32946: deflate's limit, 1032), PackBits (32773: 128), LZMA (34925) and zstd
(34926, 50000). JPEG (`_JPEG_CODES`) is bounded by its frame headers instead, every
other codec by `_UNBOUNDED_EXPANSION`."""

_JPEG_CODES = frozenset({6, 7})
"""TIFF Compression codes of JPEG (old-style 6, 7) strips or tiles: each a JPEG stream
whose frame header gives the size of the samples it decodes to (`_jpeg_frame_bytes`)."""

_UNBOUNDED_EXPANSION = 64
"""Bytes of samples read per stored byte of a codec with no bound here (JPEG 2000,
WebP, LERC, ...): the most a lying file of that codec costs; a real file that decodes to
more is refused, naming its compression."""

_JPEG_MARKERS_READ = 64
"""Marker segments of a JPEG strip or tile read at most, before its frame header."""


def _check_size(pages: Any, nbytes: int, copies: int, where: str, size: int,
                what: str) -> None:
    """Refuse `nbytes` of samples (`what`: their shape and type, as the tags give them)
    that, `copies` held at once, need more memory than available, or that are more than
    the data of `pages` (a series, or a list of pages) stored in the file (of `size`
    bytes) decode to (`_decoded_bound`). Nothing is decoded."""
    check_fits_in_memory(copies * nbytes, where, f"TIFF {what}")
    bound, unbounded = _decoded_bound(pages, size)
    if nbytes <= bound:
        return
    if unbounded:
        codes = ", ".join(map(str, unbounded))
        raise VolumeError(f"{where}: TIFF {what} needs {nbytes} bytes of samples; "
                          f"Compression {codes} has no known bound on what its data decode "
                          f"to, so at most {_UNBOUNDED_EXPANSION} bytes per stored byte, "
                          f"{bound} here, are read: the size tags are wrong, or expected "
                          "the file saved uncompressed or with LZW, Deflate, PackBits, "
                          "JPEG, LZMA or zstd")
    raise VolumeError(f"{where}: TIFF {what} needs {nbytes} bytes of samples, the "
                      f"file holds data for at most {bound}: truncated, or the image's "
                      "size tags are wrong")


def _decoded_bound(pages: Any, size: int) -> tuple[int, list[int]]:
    """(The most bytes the data of `pages` stored in a file of `size` bytes decode to,
    the Compression codes of those pages bounded by `_UNBOUNDED_EXPANSION`): for a series
    of uncompressed samples stored in one run (tifffile's ``dataoffset``, which it reads
    whole whatever the pages' strips say), the bytes from its start to the end of the
    file; else the sum of `_page_bound`."""
    start = getattr(pages, "dataoffset", None)
    if start is not None:
        return max(0, size - start), []
    bound, unbounded = 0, set()
    for page in pages:
        if page is None:
            continue
        bound += _page_bound(page, size)
        code = int(page.compression)
        if code not in _MAX_EXPANSION and code not in _JPEG_CODES:
            unbounded.add(code)
    return bound, sorted(unbounded)


def _page_bound(page: Any, size: int) -> int:
    """The most bytes the strips or tiles of `page` decode to, counting their parts
    inside the file of `size` bytes: by their JPEG frame headers (`_jpeg_frame_bytes`),
    else their bytes times `_MAX_EXPANSION` (`_UNBOUNDED_EXPANSION` where the compression
    has none)."""
    code = int(page.compression)
    segments = [(offset, max(0, min(count, size - offset)))
                for offset, count in zip(page.dataoffsets, page.databytecounts,
                                         strict=False)]
    if code in _JPEG_CODES:
        fh = page.parent.filehandle
        return sum(_jpeg_frame_bytes(fh, offset, count) for offset, count in segments)
    expansion = _MAX_EXPANSION.get(code, _UNBOUNDED_EXPANSION)
    return expansion * sum(count for _, count in segments)


def _jpeg_frame_bytes(fh: Any, offset: int, count: int) -> int:
    """The most bytes the JPEG stream of `count` bytes at `offset` in the file `fh`
    decodes to: its frame header's (SOFn, or DHP of a hierarchical image) lines x
    samples per line x components x bytes per sample (1 up to 8-bit precision, else 2);
    0 lines (given later by a DNL marker) count as 65535. 0 where the stream has no
    frame header among its first `_JPEG_MARKERS_READ` marker segments (a TIFF's
    JPEGTables hold none): no decoder makes samples of it. Reads 10 bytes per marker."""
    position, end = offset, offset + count
    for _ in range(_JPEG_MARKERS_READ):
        if end - position < 2:
            return 0
        fh.seek(position)
        head = fh.read(min(10, end - position))
        if head[0] != 0xFF:
            return 0
        marker = head[1]
        if marker == 0xFF:  # fill byte before a marker
            position += 1
        elif marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # TEM, SOI, RSTn: no length
            position += 2
        elif marker in (0xD9, 0xDA) or len(head) < 4:  # EOI, SOS: no frame header before
            return 0
        elif marker == 0xDE or (0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC)):
            return _frame_bytes(head[4:10])
        else:
            position += 2 + int.from_bytes(head[2:4], "big")
    return 0


def _frame_bytes(header: bytes) -> int:
    """Bytes of the samples a JPEG frame header's first 6 bytes (precision P bits, lines
    Y, samples per line X, components Nf) describe; 0 where they are cut short."""
    if len(header) < 6:
        return 0
    precision, lines, width, components = struct.unpack(">BHHB", header[:6])
    return (lines or 0xFFFF) * width * components * (1 if precision <= 8 else 2)


def _imagej_spacing(tif: Any) -> tuple[float, float, float] | None:
    """(x, y, z) voxel size from ImageJ metadata (resolution tags + ``spacing``), or None."""
    meta = tif.imagej_metadata
    if not meta:
        return None
    tags = tif.pages[0].tags

    def pixel_size(tag_name: str) -> float:
        tag = tags.get(tag_name)
        if tag is None:
            return 1.0
        num, den = tag.value
        return float(den) / float(num) if num else 1.0

    return (pixel_size("XResolution"), pixel_size("YResolution"), float(meta.get("spacing", 1.0)))


def load_tiff_folder(path: Path, files: list[Path]) -> Loaded:
    """Folder of 2-D TIFF slices (natural name order = z) -> (Z, Y, X).

    Each slice's shape (from its tags) is checked before it is decoded: the first's,
    times the number of files, against memory (`_check_size`: the slices and their
    stack), every other's against the first's.
    """
    tifffile = optional_module("tifffile", path)
    slices: list[np.ndarray] = []
    first: tuple[int, ...] = ()
    for file in files:
        check_readable(file)
        try:
            with tifffile.TiffFile(str(file)) as tif:
                series, size = tif.series[0], tif.filehandle.size
                shape = tuple(s for s in series.shape if s != 1) or (1,)
                if len(shape) != 2:
                    raise VolumeError(f"{file}: expected a 2-D grey-scale slice (Y, X), got "
                                      f"shape {tuple(series.shape)}")
                first = first or shape
                if shape != first:
                    raise VolumeError(f"{file}: slice shape {shape} differs from "
                                      f"{files[0].name}'s {first}; expected every slice "
                                      "the same size")
                what = f"slice shape {shape} {series.dtype}"
                copies = 2 * len(files) if not slices else 1
                _check_size(series, int(series.nbytes), copies, str(file), size, what)
                slices.append(np.asarray(series.asarray()).reshape(shape))
        except VolumeError:
            raise
        except MemoryError:
            raise VolumeError(f"{file}: TIFF slice shape {first}: not enough memory to "
                              "decode it with the slices before it") from None
        except _CODEC_ERRORS as exc:
            raise _undecodable(str(file), f"slice shape {first}", exc) from None
        except (tifffile.TiffFileError, *READ_ERRORS) as exc:
            raise VolumeError(f"{file}: not a readable TIFF slice: {one_line(exc)}") from None
    return np.stack(slices), None, None, None
