"""What tracing reads of a plan's texels, held in memory or kept in a file.

To trace a texel on a level, a bake reads its flat id, its level phase and upper weight,
its lit side and where it lands on its levels (`baking.plan.Plan`): 29 bytes a texel,
1.1 GiB for the 41 M active texels of a 512³ CT, of which a pass uses a million at a time
(`baking.backend.pass_steps`: one level at a time, a batch of texels at a time).
`HeldRecords` reads them from the plan's arrays. `SpilledRecords` keeps all but the ids
(25 bytes a texel) in an unnamed temporary file, grouped by lower level, and reads a
batch's back when it is laid out or committed — through the page cache, which the system
can let go of, not the process's own memory. Both give the same records, so a bake's
lattice is the same bits whichever holds them.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from isolume.baking.errors import BakeError
from isolume.baking.plan import Plan, index_type
from isolume.volumes import cores

RECORD = np.dtype([("phase", "<u4"), ("weight", "<f8"), ("high", "?"),
                   ("landing", "<i2", (2, 3))])
"""One texel's record in a `SpilledRecords` file, packed: 25 bytes."""
READ_ROWS = 1 << 20
"""Records read from the file at a time (25 MB): what bounds a read of texels spread
over a group."""
WRITE_ROWS = 1 << 15
"""Records one work item gathers and writes (0.8 MB: under the megabyte from which a
command's allocator maps a block alone, `app.allocator`, so that an item's block reuses
its thread's heap instead of faulting fresh pages in: the 256³ foot's settle stage took
44 k page faults with blocks of 1.6 MB written from a copy, 12 k with these)."""
GROUPS_KEPT = 2
"""Lower levels whose texel positions `LevelGroups` keeps found (those of the level a
pass traces and the one below it)."""


@dataclass(frozen=True)
class TexelRecords:
    """The plan's records of (N,) texels.

    Attributes:
        ids: (N,) flat lattice ids; phase: (N,) uint32; weight: (N,) float64; high: (N,)
            bool; landing: (N, 2, 3) int16 — as `baking.plan.Plan`'s at those texels.
    """

    ids: np.ndarray
    phase: np.ndarray
    weight: np.ndarray
    high: np.ndarray
    landing: np.ndarray


class PlanRecords(Protocol):
    """Where a bake reads its plan's records from.

    Attributes:
        high_texels: how many texels are lit on the high-value side (`Plan.high`).
    """

    high_texels: int

    def of(self, positions: np.ndarray) -> TexelRecords:
        """The records of the texels at (N,) plan `positions`, in that order."""

    def close(self) -> None:
        """Let go of what holds the records."""


class HeldRecords:
    """The records of a plan that holds its arrays (`Plan.phase`, …): read from them."""

    def __init__(self, plan: Plan) -> None:
        self.plan: Plan = plan
        self.high_texels: int = int(np.count_nonzero(plan.high))

    def of(self, positions: np.ndarray) -> TexelRecords:
        plan = self.plan
        return TexelRecords(plan.ids[positions], plan.phase[positions],
                            plan.weight[positions], plan.high[positions],
                            plan.landing[positions])

    def close(self) -> None:
        """Nothing: the plan holds them."""


class LevelGroups:
    """The sorted plan positions of some texels (`members`; None: every texel of the
    plan) by lower level, found when a level is first asked for, the last `GROUPS_KEPT`
    levels kept (no group of every level held all along). One is shared by a bake's
    records file (`SpilledRecords`) and its passes over every texel
    (`baking.backend.PassWork.lower_on`), so a level's are found once; safe to ask from
    several threads.

    Args:
        lower: (T,) the plan's lower levels (`Plan.lower`).
        members: (N,) sorted plan positions, or None.
    """

    def __init__(self, lower: np.ndarray, members: np.ndarray | None = None) -> None:
        self.lower: np.ndarray = lower
        self.members: np.ndarray | None = members
        self._kept: OrderedDict[int, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def of(self, level: int) -> np.ndarray:
        """(N,) sorted positions of the members whose lower level is `level`."""
        with self._lock:
            if level in self._kept:
                self._kept.move_to_end(level)
                return self._kept[level]
        if self.members is None:
            found = np.flatnonzero(self.lower == level).astype(index_type(len(self.lower)),
                                                               copy=False)
        else:
            found = self.members[self.lower[self.members] == level]
        with self._lock:
            self._kept[level] = found
            while len(self._kept) > GROUPS_KEPT:
                self._kept.popitem(last=False)
        return found


class SpilledRecords:
    """A plan's records in an unnamed temporary file (gone when closed, or when the
    process ends), grouped by lower level, each group in plan order: the texels of a
    batch of one group (`baking.backend.pass_steps`) are one run of the file.

    Args:
        plan: the plan whose records to keep; its arrays stay as they are (the caller
            lets go of them: `spill`).
        directory: where to make the file (the system's temporary directory if None).
        groups: the plan's texels by lower level (`LevelGroups` of every texel), shared
            with the bake's passes; made here if None.

    Raises:
        BakeError: the file cannot be made or written (e.g. the disk is full).
    """

    def __init__(self, plan: Plan, directory: str | os.PathLike[str] | None = None,
                 groups: LevelGroups | None = None) -> None:
        self.ids: np.ndarray = plan.ids
        self.lower: np.ndarray = plan.lower
        self.groups: LevelGroups = groups if groups is not None else LevelGroups(plan.lower)
        self.high_texels: int = int(np.count_nonzero(plan.high))
        counts = np.bincount(plan.lower, minlength=len(plan.levels))
        self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        where = directory if directory is not None else tempfile.gettempdir()
        self._using = threading.Condition()
        self._users = 0
        try:
            self._file = tempfile.TemporaryFile(dir=where)
            try:
                self._write(plan, len(counts))
            except BaseException:
                self.close()
                raise
        except OSError as error:
            raise BakeError(f"{where}: cannot keep the plan's texel records "
                            f"({len(plan.ids) * RECORD.itemsize / 2**20:.0f} MiB) in a "
                            f"temporary file there: {error}") from error

    def _write(self, plan: Plan, levels: int) -> None:
        """The records of every group, `WRITE_ROWS` at a time, each run gathered and
        written at its place in the file on one of the pool's threads (`os.pwrite`)."""
        runs = [(level, lo) for level in range(levels)
                for lo in range(0, int(self._starts[level + 1] - self._starts[level]),
                                WRITE_ROWS)]

        def run(i: int) -> None:
            level, lo = runs[i]
            at = self.groups.of(level)[lo:lo + WRITE_ROWS]
            block = np.empty(len(at), RECORD)
            for name in RECORD.names:
                block[name] = getattr(plan, name)[at]
            self._pwrite(block, int(self._starts[level] + lo))

        cores.for_items(run, len(runs), "records")

    @contextlib.contextmanager
    def _descriptor(self) -> Iterator[int]:
        """The file's descriptor, kept open while the caller uses it; refused once the
        file is closed (a read or write that a Ctrl-C left running must not reach a file
        opened since under the same number)."""
        with self._using:
            if self._file.closed:
                raise BakeError("the plan's temporary file is closed")
            self._users += 1
            fd = self._file.fileno()
        try:
            yield fd
        finally:
            with self._using:
                self._users -= 1
                self._using.notify_all()

    def _pwrite(self, records: np.ndarray, row: int) -> None:
        """The (B,) `records` into the file from `row` on, written from their memory (safe
        beside another thread's writes)."""
        view, offset = memoryview(records.view(np.uint8)), row * RECORD.itemsize
        with self._descriptor() as fd:
            while len(view):
                written = os.pwrite(fd, view, offset)
                view, offset = view[written:], offset + written


    def of(self, positions: np.ndarray) -> TexelRecords:
        positions = np.asarray(positions)
        lower = self.lower[positions]
        levels = np.unique(lower)
        if len(levels) == 1:  # a batch of one group (`baking.backend.pass_steps`)
            ranks = np.searchsorted(self.groups.of(int(levels[0])), positions)
            records = self._read(self._starts[levels[0]] + ranks)
        else:
            records = np.empty(len(positions), RECORD)
            for level in levels:
                these = lower == level
                ranks = np.searchsorted(self.groups.of(int(level)), positions[these])
                records[these] = self._read(self._starts[level] + ranks)
        return TexelRecords(self.ids[positions],
                            *(np.ascontiguousarray(records[name]) for name in RECORD.names))

    def close(self) -> None:
        """Close the file once no read or write is under way."""
        with self._using:
            while self._users:
                self._using.wait()
            self._file.close()

    def _read(self, rows: np.ndarray) -> np.ndarray:
        """(N,) records at file `rows` (in any order), read `READ_ROWS` at a time; a run of
        consecutive rows (a batch of one group) straight into the array it returns."""
        out = np.empty(len(rows), RECORD)
        if len(rows) and rows[-1] - rows[0] == len(rows) - 1 and (rows[1:] > rows[:-1]).all():
            self._pread_into(out, int(rows[0]))
            return out
        order = np.argsort(rows, kind="stable")
        wanted = rows[order]
        lo = 0
        while lo < len(wanted):
            first = int(wanted[lo])
            hi = int(np.searchsorted(wanted, first + READ_ROWS))
            block = np.empty(int(wanted[hi - 1]) - first + 1, RECORD)
            self._pread_into(block, first)
            out[order[lo:hi]] = block[wanted[lo:hi] - first]
            lo = hi
        return out

    def _pread_into(self, records: np.ndarray, row: int) -> None:
        """Fill the (B,) `records` with the file's from `row` on, read into their memory
        (safe beside another thread's reads)."""
        view, offset = memoryview(records.view(np.uint8)), row * RECORD.itemsize
        with self._descriptor() as fd:
            while len(view):
                read = os.preadv(fd, [view], offset)
                if not read:
                    raise BakeError(f"the plan's temporary file ended {len(view)} bytes early")
                view, offset = view[read:], offset + read


def spill(plan: Plan, directory: str | os.PathLike[str] | Path | None = None,
          groups: LevelGroups | None = None) -> tuple[Plan, SpilledRecords]:
    """`plan` without its records' arrays (phase, weight, high, landing: 25 bytes a texel)
    and the `SpilledRecords` that keep them (`groups` as there)."""
    records = SpilledRecords(plan, directory, groups)
    return replace(plan, phase=None, weight=None, high=None, landing=None), records
