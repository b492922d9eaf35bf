"""`baking.plan_records`: a plan's texel records kept in a temporary file read back as the
plan holds them, and a bake that keeps them there reads them a batch at a time."""

import numpy as np
import pytest

from isolume.baking import BakeConfig, backend, bake, plan_records
from isolume.baking.bake import Baker
from isolume.baking.errors import BakeError
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.plan import make_plan
from isolume.baking.plan_records import HeldRecords, SpilledRecords
from isolume.volumes.synthetic import make

FIELDS = ("ids", "phase", "weight", "high", "landing")


def _plan():
    volume, config = make("engine", 32), BakeConfig(samples=4, bounces=0, max_move=0.25)
    return make_plan(volume, LatticeGeometry.for_volume(volume, config.scale), config)


def test_spilled_records_read_back_what_the_plan_holds(monkeypatch, tmp_path):
    """Whole, in any order, across levels, a run of one level's (read straight into the
    records), that run backwards, empty and a few rows a read (`READ_ROWS` = 7): the file
    gives the plan's records exactly, in its types, contiguous; it leaves no name in its
    directory."""
    monkeypatch.setattr(plan_records, "READ_ROWS", 7)
    plan = _plan()
    assert len(plan.levels) >= 3
    held, spilled = HeldRecords(plan), SpilledRecords(plan, tmp_path)
    try:
        assert list(tmp_path.iterdir()) == []
        assert spilled.high_texels == held.high_texels == np.count_nonzero(plan.high)
        rng = np.random.default_rng(3)
        count = len(plan.ids)
        one_level = np.flatnonzero(plan.lower == plan.lower[count // 2])
        for positions in (np.arange(count), rng.permutation(count)[:500],
                          np.sort(rng.choice(count, 300, replace=False)), one_level[::3],
                          one_level[2:40], one_level[39:1:-1], np.zeros(0, np.int64)):
            want, got = held.of(positions), spilled.of(positions)
            for name in FIELDS:
                a, b = getattr(want, name), getattr(got, name)
                assert a.dtype == b.dtype and b.flags.c_contiguous, name
                np.testing.assert_array_equal(a, b, err_msg=name)
    finally:
        spilled.close()


@pytest.mark.parametrize("call", ["pwrite", "preadv"])
def test_a_write_or_read_left_running_never_reaches_a_file_opened_after_close(
        call, monkeypatch, tmp_path):
    """`close` waits for a write or read under way (one a Ctrl-C left running on a pool
    thread: `cores.STOP_WAIT_S`), and one that starts after it is refused: neither reaches
    a file that reuses the closed file's number."""
    import os
    import threading
    import time

    plan = _plan()
    spilled = SpilledRecords(plan, tmp_path)
    record = np.zeros(1, plan_records.RECORD)
    use = spilled._pwrite if call == "pwrite" else spilled._pread_into
    entered, release = threading.Event(), threading.Event()
    real = getattr(os, call)

    def slow(fd, data, offset):
        entered.set()
        release.wait(5)
        return real(fd, data, offset)

    monkeypatch.setattr(os, call, slow)
    user = threading.Thread(target=use, args=(record, 0))
    user.start()
    assert entered.wait(5)
    closer = threading.Thread(target=spilled.close)
    closer.start()
    time.sleep(0.2)
    assert closer.is_alive() and not spilled._file.closed  # waits for the write or read
    release.set()
    user.join(5)
    closer.join(5)
    assert spilled._file.closed
    monkeypatch.setattr(os, call, real)
    record[:] = np.zeros(1, plan_records.RECORD)
    with open(tmp_path / "other", "w+b") as other:  # may take the closed file's number
        other.write(b"x" * 4 * record.itemsize)
        other.seek(0)
        with pytest.raises(BakeError, match="closed"):
            use(record, 0)
        assert other.tell() == 0
    assert (tmp_path / "other").stat().st_size == 4 * record.itemsize
    assert not record.view(np.uint8).any()  # nothing read from the other file either


def test_a_bake_reads_its_plan_records_a_batch_at_a_time(monkeypatch, tmp_path):
    """`bake()` keeps the plan's records in a file beside its output (its plan holds none
    of their arrays) and reads those of at most one batch of texels at a time (batches
    of 37 here); the lattice is the held plan's to the bit, and the file is gone after."""
    volume, config = make("engine", 36), BakeConfig(samples=4, bounces=1)
    held = Baker(volume, config, workers=2)
    try:
        held.run()
    finally:
        held.close()
    most = [0]
    of = SpilledRecords.of

    def counted(self, positions):
        most[0] = max(most[0], len(positions))
        return of(self, positions)

    monkeypatch.setattr(SpilledRecords, "of", counted)
    monkeypatch.setattr(backend, "TEXELS_PER_BATCH", 37)
    out = tmp_path / "l.npz"
    spilled = bake(volume, config, out=out, workers=2)
    assert 0 < most[0] <= 37
    assert list(tmp_path.iterdir()) == [out]
    for name in ("values", "second", "samples", "facing", "active"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(held.lattice, name),
                                      err_msg=name)


def test_a_packed_baker_holds_no_records_arrays():
    """The Baker of `bake()` drops the plan's phase, weight, sides and landing points
    (25 bytes an active texel) once they are in the file."""
    baker = Baker(make("sphere", 16), BakeConfig(samples=2, bounces=0), workers=1,
                  packed=True)
    try:
        plan = baker.plan
        assert plan.phase is None and plan.weight is None and plan.landing is None
        assert plan.high is None and isinstance(baker.records, SpilledRecords)
    finally:
        baker.close()


def test_records_that_cannot_be_kept_are_refused_in_one_line(tmp_path):
    """A directory the file cannot be made in: a `BakeError` that names it and the size."""
    missing = tmp_path / "no" / "such"
    with pytest.raises(BakeError, match=r"no/such: cannot keep the plan's texel records "
                                        r"\(\d+ MiB\)"):
        SpilledRecords(_plan(), missing)
