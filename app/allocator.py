"""How an isolume process asks the C library's allocator to behave.

Every command (`app.cli.main`) and the viewer's bake process (`app.viewer.bake_client`)
call `tune_malloc` first; the commands that draw pictures call `for_pictures` before they
draw (``render``, and ``movie`` once the lattice it bakes, if any, is made).
"""

from __future__ import annotations

import ctypes

M_TRIM_THRESHOLD = -1
"""glibc's `mallopt` parameter (malloc.h): the free memory at the top of a heap beyond
which the heap gives it back to the system."""
M_MMAP_THRESHOLD = -3
"""glibc's `mallopt` parameter (malloc.h): the size from which a block is mapped alone."""
MAPPED_BLOCK = 1 << 20
"""Blocks of this many bytes or more are mapped alone, and unmapped when freed."""
PICTURE_MAPPED_BLOCK = 32 << 20
"""`MAPPED_BLOCK` while a command draws pictures (`for_pictures`): its blocks of a megabyte
or more — a picture's pixels, a shadow-ray item's directions, a view's texels — are made
and freed a few times a picture, not by the thousand, and mapped alone each faulted its
pages in again: the engine CT's `render` at 512², whole processes on two cores, medians
of seven pairs: 2.78 s against 3.07 s (0.26 s of CPU in the kernel against 0.51 s), peak
memory 470 against 452 MiB; the 256³ foot's at 1024²: 1.25 s in the kernel against
2.07 s, 1096 against 1165 MiB; six frames of the engine CT's turntable (`movie`, three
pairs): 12.64 s against 13.28 s, 0.39 s in the kernel against 1.02 s, 570 against
555 MiB."""
KEPT_TOP = 16 << 20
"""Free bytes a heap keeps at its top (glibc's own, once `MAPPED_BLOCK` is set: 128 KiB)."""


def tune_malloc(mapped: int = MAPPED_BLOCK) -> None:
    """Have the C library's malloc map every block of `mapped` bytes or more on its own, so
    that it goes back to the system when freed (a megabyte but while a command draws
    pictures: `for_pictures`). glibc raises that threshold to
    the size of the blocks freed (up to 32 MiB), and then keeps the batches a bake or a
    render makes and frees by the thousand (a million texels' arrays: 4–25 MB each) in
    its heaps' free lists, one heap per thread (a 256³ CT's bake: 1151 MiB at its peak
    without this, 1038 MiB with it, in the same time).

    And each heap keeps up to `KEPT_TOP` of free memory at its top: the smaller arrays a
    worker makes and frees chunk after chunk would otherwise go back to the system and
    fault in again, page by page, as the next chunk writes them (the tooth CT's bake at
    64 paths on two threads: 756 k page faults and 1.6 s of system time against 78 k and
    0.3 s, 10.6 s against 9.3 s; the 256³ foot's: 5.8–6.4 M faults and 16–17 s against
    0.8 M and 6.5 s, 140–145 s against 134–136 s, its peak 1113–1139 MiB against 1124).
    Nothing where the C library has no `mallopt`."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, TypeError, AttributeError):  # no C library by that name, or no mallopt
        return
    mallopt(M_MMAP_THRESHOLD, mapped)
    mallopt(M_TRIM_THRESHOLD, KEPT_TOP)


def for_pictures() -> None:
    """Have malloc keep blocks under `PICTURE_MAPPED_BLOCK` in its heaps from now on: what a
    command calls before it draws pictures (not the Python API, which leaves its host
    process's allocator as it is)."""
    tune_malloc(PICTURE_MAPPED_BLOCK)
