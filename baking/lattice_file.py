"""A lattice's file: the texels it holds, packed, read and written a slab at a time.

An ``.npz`` archive (zip, deflated) of format version `FORMAT_VERSION`:

- ``held``: (ceil(Z·Y·X / 8),) uint8, `numpy.packbits` of the (Z, Y, X) bool mask, in C
  order, of the texels the file holds: those active or computed (a lattice's other texels
  are zero, inactive and of unknown facing).
- ``values`` (N, C) float32, ``samples`` (N,) uint32, ``second`` (N,) float32, ``active``
  (N,) bool, ``facing`` (N, 2) uint8: the `baking.lattice.Lattice` arrays of the N held
  texels, in flat [z, y, x] order.
- ``meta``: JSON (format version, box shape and corners, kind, volume identity, statistics,
  bake config).

The texels a bake to a texel error filled from its half lattices hold zeros in ``values``
and ``second`` where the fill makes their light again to the bit (`_leaving_out`: 40 %
of the tooth CT's default file); the filled record in ``meta`` says which
(`baking.fills.LEFT_OUT`) and how, and every read here makes it again from the nodes around
them (`baking.fills.Recipe.mix`; a read of a few texels reads their nodes too).

So a file's size follows the active texels, not the lattice's box. A member is deflated in
pieces on every core (`_write_deflated`: one standard deflate stream, the same bytes on
any number of threads outside a hurried quick save, one stream of pieces across the
members; the 256³ foot's 74 MB file in 1.0 s on two threads, 1.9 s on one). A save that
a Ctrl-C waits for (`quick_saves`) stores the pieces it has not deflated yet: the same
format, about twice the bytes, 2.5–4.5× sooner (storing is ~17× faster a thread than
deflating; the disk's writes are what is left).
Members are written and read in slabs of z-layers (`SLAB_TEXELS`): neither writing a
lattice nor reading part of one makes a copy of its held texels (but for the rows its
fills are checked and made from), and a display can read
only the texels it shows (`LatticeFile.read_texels`). Files of `DENSE_VERSION` (every
array dense over the box, ``facing`` optional) are still read. A member whose header
disagrees with ``held`` or ``meta`` is refused before it is read, and a box whose dense
arrays exceed the memory available before they are made (`LatticeFile.read_dense`); a
display's read holds a slab of ``held`` at a time, whatever the box. Values and second
moments are judged as their slabs are read (`bad_texels`): a NaN or infinite one, or a
negative one in an irradiance lattice or a second moment, refuses the file, as does a
member that goes on past the rows its header counts.

Length: one format both ways: the writer and the reader share its members, slabs and
checks.
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from isolume.baking.errors import BakeError
from isolume.baking.fills import (
    FILLED_KEY,
    LEFT_OUT,
    Recipe,
    bits_of,
    corner_ids,
    kept_fills,
    marked,
    packed,
)
from isolume.volumes import cores
from isolume.volumes.io.common import available_memory
from isolume.volumes.writing import atomic_write

FORMAT_VERSION = 2
DENSE_VERSION = 1
"""The format version whose arrays are dense over the lattice's box."""
SLAB_TEXELS = 1 << 22
"""Texels of the box per slab of z-layers a member is written or read in."""
MEMBERS: dict[str, type[np.generic]] = {
    "values": np.float32, "samples": np.uint32, "second": np.float32, "active": np.bool_,
    "facing": np.uint8}
"""The per-texel arrays a file holds, with their types."""
_READ_ERRORS = (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError)


def _tail(name: str) -> tuple[int | None, ...]:
    """Per-texel shape of member `name` (None: any size ≥ 1, the values' channels)."""
    return {"values": (None,), "facing": (2,)}.get(name, ())


def _slabs(shape: tuple[int, int, int]) -> Iterator[slice]:
    """Slices of z covering a (Z, Y, X) box, `SLAB_TEXELS` texels or one layer each."""
    step = max(1, SLAB_TEXELS // max(1, shape[1] * shape[2]))
    for z0 in range(0, shape[0], step):
        yield slice(z0, min(z0 + step, shape[0]))


KINDS = ("irradiance", "sh")
"""The kinds of lattice a file may hold."""


def lattice_kind(meta: dict[str, Any]) -> str:
    """The kind of lattice a metadata dict describes: "irradiance" (also where it does not
    say) or "sh"."""
    return meta.get("kind", "irradiance")


def _flat_slabs(size: int) -> Iterator[slice]:
    """Slices of the flat texel ids 0 … `size` − 1, `SLAB_TEXELS` each (a display's read
    holds one slab's mask, however wide the box's layers)."""
    for lo in range(0, size, SLAB_TEXELS):
        yield slice(lo, min(lo + SLAB_TEXELS, size))


def bad_texels(values: np.ndarray, nonnegative: bool) -> int:
    """How many texels of the (…, C) `values` hold a NaN or infinite value, or with
    `nonnegative` a negative one: a minimum and a maximum where none does (a NaN spreads
    into both), a count only where one does."""
    if values.size == 0:
        return 0
    lo, hi = values.min(), values.max()
    if (lo >= 0 if nonnegative else lo > -np.inf) and hi < np.inf:
        return 0
    bad = ~np.isfinite(values)
    if nonnegative:
        bad |= values < 0
    return int(bad.reshape(-1, values.shape[-1]).any(axis=1).sum())


def held_mask(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(…) bool: the texels a file holds — active or computed — of `arrays` (the
    `MEMBERS`, any leading shape)."""
    return arrays["active"] | (arrays["samples"] > 0)


def write_lattice(path: str | os.PathLike[str], arrays: dict[str, np.ndarray],
                  meta: dict[str, Any]) -> None:
    """Write `arrays` (the `MEMBERS`, dense over a (Z, Y, X) box: values (Z, Y, X, C),
    facing (Z, Y, X, 2), the others (Z, Y, X)) and `meta` (JSON-ready) to `path`,
    atomically (a temporary file in the same folder, then renamed): an interrupted write
    never leaves a broken file."""
    held = held_mask(arrays)
    count = int(np.count_nonzero(held))

    def rows(name: str) -> Iterator[np.ndarray]:
        for z in _slabs(held.shape):
            yield arrays[name][z][held[z]]

    def held_rows() -> tuple[np.ndarray, dict[str, np.ndarray]]:
        ids = np.flatnonzero(held)
        return ids, {n: arrays[n].reshape(held.size, *arrays[n].shape[3:])[ids]
                     for n in _MIXED}

    meta, left = _leaving_out(meta, held.shape, count, held_rows)
    _write_archive(path, lambda: np.packbits(held.reshape(-1)), count,
                   {n: arrays[n].shape[3:] for n in MEMBERS}, _zeroed(rows, left), meta)


def write_rows(path: str | os.PathLike[str], shape: tuple[int, int, int], ids: np.ndarray,
               arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    """Write the `MEMBERS` of the texels at (N,) sorted unique flat ids `ids` of a
    (Z, Y, X) box, as (N, …) `arrays` (values (N, C), facing (N, 2), the others (N,)),
    and `meta`, as `write_lattice` does (an array may be a broadcast view: it is made a
    slab at a time). Holds no array over the box: the mask is packed from the ids a slab
    at a time (`packed_ids`)."""

    def rows(name: str) -> Iterator[np.ndarray]:
        for lo in range(0, len(ids), SLAB_TEXELS):
            yield arrays[name][lo:lo + SLAB_TEXELS]

    meta, left = _leaving_out(meta, shape, len(ids), lambda: (ids, arrays))
    _write_archive(path, lambda: packed_ids(ids, math.prod(shape)), len(ids),
                   {n: arrays[n].shape[1:] for n in MEMBERS}, _zeroed(rows, left), meta)


_MIXED = ("values", "samples", "facing", "second")
"""The members a fill is made from and of (`baking.fills.Recipe.mix`)."""
_LEFT = ("values", "second")
"""The members whose rows of filled texels a file may leave out (`_leaving_out`)."""


def _leaving_out(meta: dict[str, Any], shape: tuple[int, int, int], count: int,
                 held_rows: Callable[[], tuple[np.ndarray, dict[str, np.ndarray]]]
                 ) -> tuple[dict[str, Any], np.ndarray]:
    """`meta` as a file of the `count` held texels of a (Z, Y, X) `shape` box holds it,
    and the (F,) sorted rows of its filled texels whose light it leaves out: those whose
    values and second moments their fill makes to the bit (`baking.fills.kept_fills`,
    from ``held_rows()``: the (N,) flat ids and their `_MIXED` rows), named in the filled
    record (`LEFT_OUT`: true where they are all its filled texels, else their mask);
    none where the meta holds no fill's recipe for them, or in a hurried save
    (`quick_saves`: the check would double its time). A `LEFT_OUT` the meta brings (a
    file's) is dropped first."""
    record = meta.get(FILLED_KEY)
    if isinstance(record, dict) and LEFT_OUT in record:  # a file's, not this lattice's
        record = {k: v for k, v in record.items() if k != LEFT_OUT}
        meta = dict(meta, **{FILLED_KEY: record})
    try:
        recipe = None if _Storing.now else Recipe.of(record, count)
    except (KeyError, TypeError, ValueError, zlib.error):  # a record it cannot use: all kept
        recipe = None
    left = np.zeros(0, np.int64)
    if recipe is not None:
        left = kept_fills(recipe, shape, *held_rows())
    if not len(left):
        return meta, left
    if len(left) == int(meta[FILLED_KEY]["filled"]):
        named: bool | str = True  # every filled texel
    else:
        mask = np.zeros(count, bool)
        mask[left] = True
        named = packed(mask)
    return dict(meta, **{FILLED_KEY: dict(meta[FILLED_KEY], **{LEFT_OUT: named})}), left


def _zeroed(rows: Callable[[str], Iterator[np.ndarray]], left: np.ndarray
            ) -> Callable[[str], Iterator[np.ndarray]]:
    """`rows` with the (F,) sorted held rows `left` of the `_LEFT` members zero (copied
    chunks: the arrays written are not changed)."""

    def zeroed(name: str) -> Iterator[np.ndarray]:
        start = 0
        for chunk in rows(name):
            lo, hi = np.searchsorted(left, [start, start + len(chunk)])
            if name in _LEFT and hi > lo:
                chunk = np.array(chunk)
                chunk[left[lo:hi] - start] = 0
            start += len(chunk)
            yield chunk

    return zeroed


def packed_ids(ids: np.ndarray, size: int) -> np.ndarray:
    """(ceil(size / 8),) uint8: `numpy.packbits` of the (size,) bool mask true at the
    (N,) sorted unique flat `ids`, made `SLAB_TEXELS` ids at a time without the mask (a
    texel's bit in its byte is unique, so a byte's bits are the sum of its texels')."""
    bits = np.zeros(-(-size // 8), np.uint8)
    for lo in range(0, len(ids), SLAB_TEXELS):
        part = np.asarray(ids[lo:lo + SLAB_TEXELS], np.int64)
        byte = part >> 3
        starts = np.flatnonzero(np.concatenate([[True], byte[1:] != byte[:-1]]))
        bit = np.right_shift(np.uint8(0x80), (part & 7).astype(np.uint8))
        bits[byte[starts]] |= np.add.reduceat(bit, starts, dtype=np.uint8)
    return bits


def _write_archive(path: str | os.PathLike[str], bits: Callable[[], np.ndarray], count: int,
                   tails: dict[str, tuple], rows: Callable[[str], Iterator[np.ndarray]],
                   meta: dict[str, Any]) -> None:
    """The archive of each member `name` of per-texel shape `tails[name]` from the chunks
    `rows(name)` yields in flat order, the held texels' mask (``bits()``: the packed bits
    of the (Z, Y, X) bool mask of the `count` held texels, made on a pool thread while the
    cores deflate the first members, so that no core waits for it at the end — 0.13 s of
    the 256³ foot's 1 s save — or on this thread when its member comes, if no pool thread
    has begun it) and `meta`, written to a temporary file that then replaces `path`."""
    path = Path(path)
    meta = dict(meta, format_version=FORMAT_VERSION)
    pool = cores.pool() if cores.threads() > 1 else cores.Inline()
    mask = pool.submit(cores.beside_call, "held mask", bits)

    def member(dtype: np.dtype, shape: tuple[int, ...], chunks: Iterable[np.ndarray]
               ) -> Iterator[memoryview]:
        yield memoryview(_header(dtype, shape))
        for chunk in chunks:
            yield memoryview(np.ascontiguousarray(chunk, dtype).reshape(-1).view(np.uint8))

    def held() -> Iterator[memoryview]:
        packed = bits() if mask.cancel() else mask.result()
        yield from member(packed.dtype, packed.shape, [packed])

    members = {name: member(np.dtype(dtype), (count, *tails[name]), rows(name))
               for name, dtype in MEMBERS.items()}
    members["held"] = held()

    def write(tmp: str) -> None:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
            _write_deflated(zf, members)
            with zf.open("meta.npy", "w", force_zip64=True) as opened:
                np.lib.format.write_array(opened, np.array(json.dumps(meta)),
                                          allow_pickle=False)

    try:
        atomic_write(path, write, "lattice", kept=" (a bake resumes from it)", durable=True)
    finally:  # a save that failed or was stopped leaves no mask to be made
        mask.cancel()


DEFLATE_PIECE = 1 << 20
"""Bytes of a member deflated as one piece, on one of the pool's threads
(`_write_deflated`)."""
PIECES_AHEAD = 6
"""Pieces per thread handed to the pool ahead of the one being written: pieces of zeros
deflate several times faster than others, and a shorter queue leaves cores idle (the 256³
foot's file on two threads: 0.95 of two cores busy, against 0.90 with 2 a thread); at
most that many deflated megabytes a thread wait to be written."""
_FINAL_BLOCK = zlib.compressobj(zlib.Z_DEFAULT_COMPRESSION, zlib.DEFLATED, -15).flush()
"""An empty final deflate block: what ends a stream of pieces that each end in a sync
flush."""


class _Storing:
    """Whether saves store the pieces they have not deflated yet (`quick_saves`): a plain
    flag, set by a signal handler and read by pool threads, so that neither takes a
    lock."""

    now = False


def _hurry() -> None:
    """Have saves store, from now on, the pieces they have not deflated yet."""
    _Storing.now = True


@contextmanager
def quick_saves(now: bool) -> Iterator[Callable[[], None]]:
    """In the body, lattice files are saved quickly: from the start where `now`, else from
    when the function this yields is called (by a Ctrl-C that waits for a save), the
    pieces not deflated yet are stored (deflate level 0: the same stream format, which
    `numpy.load` reads, ~17× faster a thread than deflating — 870 MB/s against 50 — in
    about twice the bytes: 966 MB against 504 MB for the 512³ foot's lattice, stored in
    0.9–1.4 s, 1.5–2.7 s right after other large writes, against 6.8 s deflated on two
    threads). A bake of the file run again writes
    it deflated. The setting is the process's, as a Ctrl-C is; after the body it is what
    it was before. Not where zipfile lacks what the pieces need (`_write_deflated`: then
    it deflates each member itself)."""
    was = _Storing.now
    if now:
        _hurry()
    try:
        yield _hurry
    finally:
        _Storing.now = was


RUN_LENGTH_MEMBERS = frozenset({"second", "facing"})
"""Members deflated with runs only (level 1, `zlib.Z_RLE`): path second moments and
octahedral normal codes hold few longer repeats, so this takes a quarter to a third of
the default level's time for at most 1.4 % more of their bytes (the 512³ foot's
lattice: second 143 MB/s a thread to 0.714 of its size, against 37 MB/s to 0.704; facing
161 against 56 MB/s, both to 0.999); the others compress well at the default level
(values to 0.58, against 0.73 with runs only)."""


class _Piece(NamedTuple):
    """A piece of a member's bytes (`member`: its index) and its deflation."""

    member: int
    data: memoryview
    deflated: Future


def _write_deflated(zf: zipfile.ZipFile, members: dict[str, Iterator[memoryview]]) -> None:
    """Members ``NAME.npy`` of the bytes each of `members` yields, deflated in pieces on
    every core: the bytes are cut into pieces of `DEFLATE_PIECE`, each deflated on its own
    (`_deflated`: blocks ended by a sync flush, so that a member's pieces, in order, and
    `_FINAL_BLOCK` make one valid deflate stream, the same bytes on any number of threads)
    in one stream across the members — the next member's first pieces are deflating while
    this one's last are written, so the cores do not wait at each member's end — while
    this thread keeps the members' CRCs and writes the pieces done, in order, and, rather
    than wait for the oldest piece, deflates the newest one no thread has started. The
    `RUN_LENGTH_MEMBERS` are deflated with runs only.

    `zipfile` writes each member's header and sizes: the member it opened gets the pieces
    through a compressor that passes them on, and the CRC and size of the bytes before
    deflation once they are all written (``_ZipWriteFile``'s ``_compressor``, ``_crc`` and
    ``_file_size``, unchanged since Python 3.6; where they are missing, zipfile deflates
    each member itself, on this thread)."""
    pool = cores.pool() if cores.threads() > 1 else cores.Inline()
    batch = cores.new_batch()  # the pieces, side by side in a timeline
    sums = [[0, 0] for _ in members]  # each member's CRC and size, as its pieces are cut
    pieces = _cut(members.values(), sums)
    runs = [name in RUN_LENGTH_MEMBERS for name in members]
    pending: deque[_Piece] = deque()
    try:
        for index, name in enumerate(members):
            with zf.open(name + ".npy", "w", force_zip64=True) as opened:
                if not all(hasattr(opened, a) for a in ("_compressor", "_crc", "_file_size")):
                    for data in members[name]:  # so for every member: `pieces` not begun
                        opened.write(data)
                    continue
                opened._compressor = _Passing()
                while True:
                    while len(pending) < PIECES_AHEAD * cores.threads():
                        cut = next(pieces, None)
                        if cut is None:
                            break
                        member, data = cut
                        pending.append(_Piece(member, data, pool.submit(
                            _deflated, data, runs[member], batch)))
                    if not pending or pending[0].member != index:
                        break
                    opened.write(_oldest(pending, runs, batch))
                opened.write(_FINAL_BLOCK)
                opened._crc, opened._file_size = sums[index]
    finally:
        for piece in pending:  # after an error: no piece left running
            piece.deflated.cancel()


def _cut(members: Iterable[Iterator[memoryview]], sums: list[list[int]]
         ) -> Iterator[tuple[int, memoryview]]:
    """(member index, piece) of every member's bytes in order, cut into `DEFLATE_PIECE`
    pieces; each member's CRC and size in `sums` [CRC, size] as they are cut."""
    for index, buffers in enumerate(members):
        for data in buffers:
            for lo in range(0, len(data), DEFLATE_PIECE):
                piece = data[lo:lo + DEFLATE_PIECE]
                sums[index][0] = zlib.crc32(piece, sums[index][0])
                sums[index][1] += len(piece)
                yield index, piece


def _oldest(pending: deque[_Piece], runs: list[bool], batch: int) -> bytes:
    """The oldest pending piece, deflated, taken out; while it is not done, this thread
    deflates the newest piece not started yet (taken from the pool's queue; `runs`: which
    members are deflated with runs only), the oldest itself last (so a save whose pool
    threads are all busy elsewhere still ends)."""
    oldest = pending[0].deflated
    while not oldest.done():
        queued = next((i for i in range(len(pending) - 1, -1, -1)
                       if pending[i].deflated.cancel()), None)  # the oldest: then done
        if queued is None:
            break
        done: Future = Future()
        piece = pending[queued]
        done.set_result(_deflated(piece.data, runs[piece.member], batch))
        pending[queued] = pending[queued]._replace(deflated=done)
    return pending.popleft().deflated.result()


def _not_a_lattice(path: Path) -> str:
    """Why `path`, not a zip archive, is no lattice: a truncated one (it starts as a zip
    archive, a local file header, but has no end: a copy cut short, a full disk) or
    something else."""
    try:
        with open(path, "rb") as f:
            start = f.read(4)
    except OSError:
        start = b""
    if start == b"PK\x03\x04":
        return (f"{path}: a truncated or damaged lattice file: it starts as the .npz "
                "archive isolume bake writes, but its end is missing (a copy cut short, a "
                "full disk); delete it, or give another file")
    return f"{path}: not a lattice file: expected the .npz archive that isolume bake writes"


class _Passing:
    """A zipfile compressor that passes bytes already deflated through."""

    @staticmethod
    def compress(data) -> bytes:
        return data

    @staticmethod
    def flush() -> bytes:
        return b""


def _deflated(piece, runs: bool, batch: int) -> bytes:
    """`piece` deflated on its own (raw deflate at zipfile's level; with `runs`, as the
    `RUN_LENGTH_MEMBERS` are; stored in a quick save: `quick_saves`), ended by a sync
    flush: byte-aligned and not final, so that pieces concatenate into one stream; an
    item of `batch` in a timeline."""
    level, strategy = zlib.Z_DEFAULT_COMPRESSION, zlib.Z_DEFAULT_STRATEGY
    if _Storing.now:
        level = zlib.Z_NO_COMPRESSION
    elif runs:
        level, strategy = 1, zlib.Z_RLE
    with cores.batch_item(batch, "deflate"):
        deflate = zlib.compressobj(level, zlib.DEFLATED, -15, 8, strategy)
        return deflate.compress(piece) + deflate.flush(zlib.Z_SYNC_FLUSH)


def _header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
    """The .npy header of a C-ordered array of `dtype` and `shape` whose data follows."""
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(out, {
        "descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
        "shape": shape})
    return out.getvalue()


@dataclass(frozen=True)
class LatticeFile:
    """A lattice file opened and checked, its arrays not read.

    Attributes:
        path: the file.
        meta: its metadata (as `baking.lattice.Lattice.meta`, the bake config's dict and
            version still in it under ``config`` and ``config_version``).
        shape: (Z, Y, X) texels of the lattice's box.
        version: its format version (`FORMAT_VERSION` or `DENSE_VERSION`).
        channels: values per texel, as the values' header says (1 where it gives none).
        left_out: the `LEFT_OUT` entry of its filled record (taken out of `meta`): the
            filled texels whose values and second moments it leaves out, which its reads
            make again (`baking.fills`): True (all of them) or their packed mask; None
            where it leaves none out.
    """

    path: Path
    meta: dict[str, Any]
    shape: tuple[int, int, int]
    version: int
    channels: int
    left_out: bool | str | None = None

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> LatticeFile:
        """Read and check `path`'s metadata.

        Raises:
            BakeError: missing file, not a lattice file, unknown format version.
        """
        path = Path(path)
        if not path.is_file():
            raise BakeError(f"{path}: lattice file not found")
        if not zipfile.is_zipfile(path):
            raise BakeError(_not_a_lattice(path))
        try:
            with zipfile.ZipFile(path) as zf:
                with zf.open("meta.npy") as member:
                    meta = json.loads(str(np.lib.format.read_array(member,
                                                                   allow_pickle=False)))
                with zf.open("values.npy") as member:
                    values = _Rows(member, "values", np.float32).shape
            shape = tuple(meta["shape"])
            channels = int(values[-1]) if len(values) in (2, 4) else 1
        except (*_READ_ERRORS, TypeError) as exc:
            raise BakeError(f"{path}: not a readable isolume lattice ({exc})") from None
        version = meta.get("format_version")
        if version not in (FORMAT_VERSION, DENSE_VERSION):
            raise BakeError(f"{path}: lattice format version {version}, this isolume reads "
                            f"{DENSE_VERSION} and {FORMAT_VERSION}")
        if len(shape) != 3 or not all(type(n) is int and n >= 1 for n in shape):
            raise BakeError(f"{path}: lattice shape {meta['shape']}: expected three whole "
                            "numbers ≥ 1")
        if lattice_kind(meta) not in KINDS:
            raise BakeError(f"{path}: lattice kind {lattice_kind(meta)!r}: expected one of "
                            f"{', '.join(KINDS)}")
        record = meta.get(FILLED_KEY)
        left_out = None
        if isinstance(record, dict) and LEFT_OUT in record:
            record = dict(record)
            left_out = record.pop(LEFT_OUT)
            meta[FILLED_KEY] = record
        return cls(path, meta, shape, int(version), channels, left_out)

    def read_dense(self, out: dict[str, np.ndarray] | None = None
                   ) -> dict[str, np.ndarray | None]:
        """The `MEMBERS` dense over the box (values (Z, Y, X, C), facing (Z, Y, X, 2), the
        others (Z, Y, X); texels not held zero, facing unknown), in new arrays or written
        into the zero arrays `out` of those shapes (another process's shared memory: no
        copy of the box is made). A file of `DENSE_VERSION` without ``facing`` gives None
        for it (`out`'s is left as it is).

        Raises:
            BakeError: a box larger than the memory available (before anything is
                allocated), a member missing, of another type or shape, or cut short,
                or values that are not finite (or negative: irradiance; `bad_texels`).
        """
        try:
            with zipfile.ZipFile(self.path) as zf:
                if out is None:
                    self._check_fits()
                slabs = None if self.version == DENSE_VERSION else list(self._held_slabs(zf))
                counts = None if slabs is None else [int(m.sum()) for _, m in slabs]
                out = dict(out or {})
                for name in MEMBERS:
                    if counts is None and name == "facing" and "facing.npy" not in zf.namelist():
                        out.setdefault(name, None)
                        continue
                    with self._member(zf, name, counts) as rows:
                        if name not in out:
                            out[name] = np.zeros((*self.shape, *rows.tail), rows.dtype)
                        elif out[name].shape != (*self.shape, *rows.tail):
                            raise BakeError(f"{self.path}: {name} of the box "
                                            f"{(*self.shape, *rows.tail)}, the arrays to "
                                            f"fill are {out[name].shape}")
                        if counts is None:
                            for z in _slabs(self.shape):
                                out[name][z] = rows.read(z.stop - z.start)
                        else:
                            flat = _flat_view(out[name], rows.tail)
                            for (part, mask), count in zip(slabs, counts, strict=True):
                                flat[part][mask] = rows.read(count)
                        rows.finish(self.path)
                if self.left_out is not None and slabs is not None:
                    self._refill_dense(out, slabs)
                return out
        except BakeError:
            raise
        except _READ_ERRORS as exc:
            raise BakeError(f"{self.path}: not a readable isolume lattice ({exc})") from None

    def read_texels(self, texels: np.ndarray | None,
                    names: tuple[str, ...] = ("values", "samples", "facing")
                    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The members `names` at the held texels among (K,) sorted flat ids `texels`
        (None: every held texel), read a slab at a time: memory follows the texels read
        and a slab, not the box.

        Returns:
            ((M,) int64 sorted flat ids of the texels read, {name: (M, …) array}).

        Raises:
            BakeError: as `read_dense`.
        """
        if self.version == DENSE_VERSION:
            return self._dense_texels(texels, names)
        try:
            with zipfile.ZipFile(self.path) as zf:
                picks = list(self._picks(zf, texels))
                if self.left_out is None or not set(names) & set(_LEFT):
                    return self._read_picks(zf, picks, names)
                recipe = self._recipe(sum(count for _, _, count in picks))
                if texels is not None:  # the nodes of the texels left out too
                    more = self._with_nodes(recipe, picks)
                    if more is None:
                        return self._read_picks(zf, picks, names)
                    picks = list(self._picks(zf, more))
                ids, out = self._read_picks(zf, picks, tuple(dict.fromkeys((*names, *_MIXED))))
                self._refill(recipe, ids, None if texels is None else self._positions(picks),
                             out)
                asked = (slice(None) if texels is None
                         else np.isin(ids, texels, assume_unique=True))
                return ids[asked], {n: out[n][asked] for n in names}
        except BakeError:
            raise
        except _READ_ERRORS as exc:
            raise BakeError(f"{self.path}: not a readable isolume lattice ({exc})") from None

    def _read_picks(self, zf: zipfile.ZipFile, picks: list[tuple[np.ndarray, np.ndarray, int]],
                    names: tuple[str, ...]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The members `names` at the texels `picks` chooses (`_picks`): their (M,) flat
        ids and {name: (M, …) rows}."""
        counts = [count for _, _, count in picks]
        out = {}
        for name in names:
            with self._member(zf, name, counts) as rows:
                out[name] = np.concatenate(
                    [rows.read(count)[chosen] for _, chosen, count in picks])
                rows.finish(self.path)
        return np.concatenate([p[0] for p in picks]), out

    def _recipe(self, held: int) -> Recipe:
        """The recipe of the fills the file leaves out, of its `held` texels.

        Raises:
            BakeError: a filled record that does not hold one for them.
        """
        try:
            recipe = Recipe.of(self.meta.get(FILLED_KEY), held)
            gone = recipe is not None and (self.left_out is True or len(
                bits_of(self.left_out)) == len(recipe.filled))
        except (KeyError, TypeError, ValueError, zlib.error) as exc:
            raise BakeError(f"{self.path}: its filled texels' record is unreadable ({exc}); "
                            "the file is damaged: bake it again") from None
        if recipe is None:
            raise BakeError(f"{self.path}: it leaves its filled texels out, and its filled "
                            f"record is not of its {held:,} texels; the file is damaged: "
                            "bake it again")
        if len(recipe.weights) != self.channels or not gone:
            raise BakeError(f"{self.path}: its filled record's brightness weights or list "
                            f"of texels left out are not of its {self.channels} channels and "
                            f"{held:,} texels; the file is damaged: bake it again")
        return recipe

    @staticmethod
    def _positions(picks: list[tuple[np.ndarray, np.ndarray, int]]) -> np.ndarray:
        """(M,) the positions among the held texels of the texels `picks` chooses."""
        firsts = np.cumsum([0] + [count for _, _, count in picks[:-1]])
        return np.concatenate([chosen + first for (_, chosen, _), first
                               in zip(picks, firsts, strict=True)]).astype(np.int64)

    def _with_nodes(self, recipe: Recipe, picks: list[tuple[np.ndarray, np.ndarray, int]]
                    ) -> np.ndarray | None:
        """The sorted flat ids of the texels `picks` chooses and of the places of the
        nodes of those of them the file leaves out (`baking.fills.corner_ids`); None
        where it leaves none of them out."""
        ids = np.concatenate([p[0] for p in picks])
        positions = self._positions(picks)
        gone = marked(self._gone(recipe), positions)
        if not gone.any():
            return None
        return np.union1d(ids, corner_ids(ids[gone], self.shape,
                                          recipe.odd_filled(positions[gone])))

    def _gone(self, recipe: Recipe) -> np.ndarray:
        """The packed bits of the held texels the file leaves out."""
        return recipe.filled if self.left_out is True else bits_of(self.left_out)

    def _refill(self, recipe: Recipe, ids: np.ndarray, positions: np.ndarray | None,
                rows: dict[str, np.ndarray]) -> None:
        """Make again, in (M, …) `rows` of the texels at sorted flat `ids` (held
        `positions`; None: all held texels in order), the values and second moments
        (where `rows` holds them) of those the file leaves out, from their nodes'."""
        gone = self._gone(recipe)
        which = np.flatnonzero(np.unpackbits(gone, count=len(ids)) if positions is None
                               else marked(gone, positions))

        def take(at: np.ndarray, values: np.ndarray, second: np.ndarray | None) -> None:
            rows["values"][at] = values
            if "second" in rows:
                rows["second"][at] = second

        recipe.mix(self.shape, ids, positions, rows, which, take)

    def _refill_dense(self, arrays: dict[str, np.ndarray],
                      slabs: list[tuple[slice, np.ndarray]]) -> None:
        """`_refill` the dense (Z, Y, X, …) `arrays` of `read_dense`, whose held texels
        `slabs` marks (`_held_slabs`: no page of the arrays is read to find them): the
        rows of the texels left out and of their nodes are copied out, mixed and written
        back (the others are not copied)."""
        ids = np.concatenate([np.flatnonzero(mask) + part.start for part, mask in slabs])
        recipe = self._recipe(len(ids))
        gone = np.flatnonzero(np.unpackbits(self._gone(recipe), count=len(ids)))
        places = np.concatenate([ids[gone], corner_ids(ids[gone], self.shape,
                                                       recipe.odd_filled(gone))])
        at = np.minimum(np.searchsorted(ids, places), max(len(ids) - 1, 0))
        wanted = np.zeros(len(ids), bool)
        wanted[at[ids[at] == places]] = True  # corners outside the plan hold no node
        positions = np.flatnonzero(wanted)
        near = ids[positions]
        del ids, places, at, wanted
        flat = {n: _flat_view(arrays[n], arrays[n].shape[3:]) for n in _MIXED}
        rows = {n: flat[n][near] for n in _MIXED}
        self._refill(recipe, near, positions, rows)
        for name in _LEFT:
            flat[name][near] = rows[name]

    def _dense_texels(self, texels: np.ndarray | None, names: tuple[str, ...]
                      ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """`read_texels` of a `DENSE_VERSION` file (read whole)."""
        dense = self.read_dense()
        if dense["facing"] is None:
            dense["facing"] = np.zeros((*self.shape, 2), np.uint8)
        held = held_mask(dense).reshape(-1)
        ids = np.flatnonzero(held) if texels is None else \
            np.asarray(texels, np.int64)[held[np.asarray(texels, np.int64)]]
        return ids, {n: dense[n].reshape(len(held), *dense[n].shape[3:])[ids] for n in names}

    def _check_fits(self) -> None:
        """Refuse a box whose dense arrays (C values per texel, as the values' header
        says) exceed the memory this machine has available."""
        channels = self.channels
        per_texel = sum(np.dtype(dtype).itemsize * math.prod(t or channels for t in _tail(n))
                        for n, dtype in MEMBERS.items())
        need = int(np.prod(self.shape, dtype=np.int64)) * per_texel
        free = available_memory()
        if free is not None and need > free:
            raise BakeError(f"{self.path}: a lattice of {self.shape[::-1]} texels needs "
                            f"{need / 1e9:.3g} GB dense, more than the {free / 1e9:.3g} GB "
                            "of memory available (render --lattice reads only the texels "
                            "a picture shows)")

    def _picks(self, zf: zipfile.ZipFile, texels: np.ndarray | None
               ) -> Iterator[tuple[np.ndarray, np.ndarray, int]]:
        """Per slab of the held texels, first to last: (flat ids of the texels read,
        their rows among the slab's held texels, the slab's held count)."""
        for part, mask in self._held_slabs(zf):
            local = np.flatnonzero(mask)
            if texels is None:
                yield local + part.start, np.arange(len(local)), len(local)
                continue
            lo, hi = np.searchsorted(texels, [part.start, part.stop])
            want = np.asarray(texels[lo:hi], np.int64) - part.start
            rows = np.minimum(np.searchsorted(local, want), max(len(local) - 1, 0))
            hit = local[rows] == want if len(local) else np.zeros(len(want), bool)
            yield want[hit] + part.start, rows[hit], len(local)

    def _held_slabs(self, zf: zipfile.ZipFile) -> Iterator[tuple[slice, np.ndarray]]:
        """(slice of flat texel ids, (n,) bool mask of the held texels among them) per
        slab (`_flat_slabs`), the packed bits read as they are needed.

        Raises:
            BakeError: ``held`` longer than the box, or with bits set past its last texel.
        """
        size = math.prod(self.shape)
        nbytes = -(-size // 8)
        with zf.open("held.npy") as member:
            rows = _Rows(member, "held", np.uint8).check((nbytes,), (), self.path)
            bits = np.zeros(0, np.uint8)
            for part in _flat_slabs(size):
                need = part.stop - part.start
                fresh = rows.read(min(-(-(need - len(bits)) // 8), nbytes))
                nbytes -= len(fresh)
                bits = np.concatenate([bits, np.unpackbits(fresh)])
                yield part, bits[:need].astype(bool)
                bits = bits[need:]
            rows.finish(self.path)
            if bits.any():
                raise BakeError(f"{self.path}: held marks texels past the last of the box's "
                                f"{size:,}; the file is damaged: bake it again")

    def _member(self, zf: zipfile.ZipFile, name: str, counts: list[int] | None) -> _Rows:
        """Member `name`'s rows, its header checked: rows of the held texels (the sum of
        the slabs' `counts`), or of z-layers of the box (`counts` None: a `DENSE_VERSION`
        file). The values' rows are judged as they are read (`_Rows.nonnegative`: by the
        lattice's kind), and the second moments'."""
        lead = self.shape if counts is None else (sum(counts),)
        member = zf.open(name + ".npy")
        try:
            rows = _Rows(member, name, MEMBERS[name]).check(lead, _tail(name), self.path)
        except BaseException:
            member.close()
            raise
        if name == "values":
            rows.nonnegative = lattice_kind(self.meta) == "irradiance"
            rows.expected = ("finite irradiance ≥ 0" if rows.nonnegative
                             else "finite SH coefficients")
        elif name == "second":
            rows.nonnegative, rows.expected = True, "finite second moments ≥ 0"
        return rows


def _flat_view(array: np.ndarray, tail: tuple[int, ...]) -> np.ndarray:
    """(Z·Y·X, *`tail`) view of a C-ordered (Z, Y, X, *`tail`) `array` (a write into it
    reaches `array`).

    Raises:
        ValueError: `array` is not C-ordered (a reshape would copy it).
    """
    if not array.flags.c_contiguous:
        raise ValueError("a lattice file is read into C-ordered arrays only")
    return array.reshape(-1, *tail)


class _Rows:
    """The rows of one .npy member (along its first axis), read in order without loading
    it whole.

    Attributes:
        nonnegative: rows judged as they are read (`bad_texels`): finite and ≥ 0 (True:
            irradiance, second moments), finite (False: SH coefficients, which may be
            negative), or not judged (None).
        expected: what a judged row holds, in words (for `finish`'s message).
        judged, bad: texels read and judged, and how many of them are bad (`bad_texels`).
    """

    def __init__(self, member, name: str, dtype) -> None:
        self.member, self.name, self.want = member, name, np.dtype(dtype)
        version = np.lib.format.read_magic(member)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        self.shape, self.fortran, self.dtype = read_header(member)
        self.tail: tuple[int, ...] = ()
        self.row = 0
        self.nonnegative: bool | None = None
        self.expected = ""
        self.judged = self.bad = 0

    def check(self, lead: tuple[int, ...], tail: tuple[int | None, ...], path: Path
              ) -> _Rows:
        """Self, if the member is a C-ordered array of the expected type whose shape is
        `lead` then `tail` (None in `tail`: any size ≥ 1).

        Raises:
            BakeError: naming the member, its shape and type, and what was expected.
        """
        shape = tuple(self.shape)
        fits = (len(shape) == len(lead) + len(tail) and shape[:len(lead)] == tuple(lead)
                and all((t is None and n >= 1) or n == t
                        for n, t in zip(shape[len(lead):], tail, strict=True)))
        if self.fortran or self.dtype != self.want or not fits:
            expected = ", ".join([*map(str, lead), *("C" if t is None else str(t) for t in tail)])
            raise BakeError(f"{path}: {self.name} of shape {shape} and type {self.dtype} does "
                            f"not match the lattice (expected ({expected}) of {self.want})")
        self.tail = shape[len(lead):]
        self.row = int(np.prod(shape[1:], dtype=np.int64)) * self.dtype.itemsize
        return self

    def read(self, count: int) -> np.ndarray:
        """The next `count` rows."""
        data = self.member.read(count * self.row)
        if len(data) != count * self.row:
            raise EOFError(f"{self.name} ends early")
        rows = np.frombuffer(data, self.dtype).reshape(count, *self.shape[1:]).copy()
        if self.nonnegative is not None:
            per_texel = rows.reshape(-1, math.prod(self.tail))
            self.judged += len(per_texel)
            self.bad += bad_texels(per_texel, self.nonnegative)
        return rows

    def finish(self, path: Path) -> None:
        """Raise BakeError if any row read so far is bad (`nonnegative`), or if the
        member goes on past the rows its header counts (read after all of them).

        Raises:
            BakeError: naming the file and the member, how many of the texels read are
                bad or that bytes follow the rows, and what was expected.
        """
        if self.bad:
            what = "NaN, infinite or negative" if self.nonnegative else "NaN or infinite"
            noun = "values" if self.name == "values" else "second moments"
            raise BakeError(f"{path}: {self.bad:,} of the {self.judged:,} texels read hold "
                            f"{what} {noun}, expected {self.expected}; the file is "
                            "damaged: bake it again")
        if self.member.read(1):
            raise BakeError(f"{path}: {self.name}.npy goes on past the {self.shape} array "
                            "its header gives; the file is damaged: bake it again")

    def __enter__(self) -> _Rows:
        return self

    def __exit__(self, *exc) -> None:
        self.member.close()
