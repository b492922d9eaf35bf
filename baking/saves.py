"""A bake's saves of its lattice: its checkpoints while it traces (`Checkpoints`) and its
final save, which a Ctrl-C does not cut short (`through_one_interrupt`). Each save writes
the whole file beside the old one and renames it (`volumes.writing.atomic_write`), so a
save cut short or failed leaves the last one."""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from isolume.baking.errors import SaveAbandoned
from isolume.baking.lattice_file import quick_saves
from isolume.volumes import cores, interrupts
from isolume.volumes.errors import WriteError


class Saved(Protocol):
    """What `Checkpoints` saves: a lattice (`baking.Lattice`, `baking.PlanLattice`), its
    `samples` the paths of each texel (0: not computed)."""

    samples: np.ndarray

    def save(self, path: Path) -> None: ...


CHECKPOINT_S = 60.0
"""Seconds between a bake's checkpoints, at least (`Checkpoints`)."""
SAVE_SHARE = 0.05
"""The most of a bake's time its checkpoints take (`Checkpoints`)."""


class Checkpoints:
    """A bake's saves of its lattice to `out` as texels are committed (an ``after_commit``
    of `baking.bake.Baker.run`): at least `seconds` apart, and apart by at least 1 /
    `SAVE_SHARE` times the last save's duration, so that saving a large lattice takes at
    most 5 % of the bake (the 512³ foot's file takes ~7 s to write on two threads: a save
    every ~2.3 min, not every minute); none when `out` is None."""

    def __init__(self, lattice: Saved, out: Path | None, seconds: float) -> None:
        self.lattice: Saved = lattice
        self.out: Path | None = out
        self.seconds: float = seconds
        self.due: float = time.perf_counter() + seconds
        self.saves: int = 0

    def __call__(self, _committed: np.ndarray) -> None:
        began = time.perf_counter()
        if self.out is None or began < self.due:
            return
        try:
            with cores.timed_item("checkpoint"):
                self.lattice.save(self.out)
        except WriteError:  # the file could not be written: the error ends the bake
            self.due = math.inf
            raise
        self.saves += 1
        ended = time.perf_counter()
        self.due = ended + max(self.seconds, (ended - began) / SAVE_SHARE)


@contextmanager
def through_one_interrupt(note: str | None, on_press: Callable[[], None] | None = None
                          ) -> Iterator[list[bool]]:
    """Run the body to its end through one Ctrl-C (SIGINT): the first is recorded in the
    list this yields (`note`, where not None, printed on stderr; `on_press` called: e.g.
    the hurry of `baking.lattice_file.quick_saves`), a second raises KeyboardInterrupt at
    once. So the final save of a finished bake is not lost to a Ctrl-C that arrives while
    it writes (seconds for a large lattice, the bar at 100 %).
    Only on the main thread where a stop raises KeyboardInterrupt
    (`interrupts.raises_keyboard_interrupt`: Python's own SIGINT handler, the command
    line's, or the command line's SIGTERM where SIGINT is ignored; a signal handler is the
    main thread's, restored after); under another handler — an application's, or an
    outer `through_one_interrupt`'s, which then records the press — the body runs as that
    one has it."""
    pressed: list[bool] = []
    before = signal.getsignal(signal.SIGINT)
    if (threading.current_thread() is not threading.main_thread()
            or not interrupts.raises_keyboard_interrupt(before)):
        yield pressed
        return

    def deferred(signum: int, frame: Any) -> None:
        if pressed:
            interrupts.on_interrupt(signum, frame)  # KeyboardInterrupt, after a callback
            return
        pressed.append(True)
        if on_press is not None:
            on_press()
        if note is not None:
            print(f"\n{note}", file=sys.stderr, flush=True)

    signal.signal(signal.SIGINT, deferred)
    try:
        yield pressed
    finally:
        signal.signal(signal.SIGINT, before)


def save_interrupted(lattice: Saved, out: Path, progress: bool) -> None:
    """Save the finished texels of a bake a Ctrl-C stopped to `out`, quickly (what is not
    deflated yet stored: `lattice_file.quick_saves`), saying so on stderr with
    `progress`. A second Ctrl-C stops the save: `errors.SaveAbandoned`, `out` as it was."""
    if progress:
        print(f"isolume: interrupted; saving the finished texels to {out}, uncompressed "
              "(Ctrl-C again to stop without them)", file=sys.stderr, flush=True)
    with quick_saves(now=True):
        save_through(lattice, out)


def save_through(lattice: Saved, out: Path) -> None:
    """The final save of a finished bake to `out` (inside `through_one_interrupt`: a first
    Ctrl-C lets it end); a second Ctrl-C stops it: `errors.SaveAbandoned`, `out` as it
    was."""
    try:
        lattice.save(out)
    except KeyboardInterrupt:
        raise SaveAbandoned(int(np.count_nonzero(lattice.samples))) from None

