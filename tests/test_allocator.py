"""`app.allocator`: what an isolume process asks of the C library's malloc."""

import subprocess
import sys

import pytest

WORKER = """
import resource, sys, threading
import numpy as np
from isolume.app.allocator import tune_malloc
if sys.argv[1] == "set":
    tune_malloc()
faults = []
def chunks():
    for i in range(60):  # a chunk's arrays under a megabyte, made, written and freed
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        arrays = [np.ones(1 << 16) for _ in range(8)]  # 8 x 512 KiB
        del arrays
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
worker = threading.Thread(target=chunks)
worker.start()
worker.join()
print(sum(faults[10:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_workers_chunks_under_a_megabyte_do_not_fault_their_pages_in_again():
    """With `tune_malloc`, a worker thread that makes and frees its arrays under
    a megabyte chunk after chunk reuses its heap's pages instead of faulting them in again
    (4 MiB a chunk: 1024 pages of 4 KiB); blocks of a megabyte and more are still mapped
    alone and given back when freed."""
    pages = 50 * (8 << 19) // 4096  # the 50 chunks after the first ten
    faults = int(subprocess.run([sys.executable, "-c", WORKER, "set"], check=True,
                                capture_output=True, text=True).stdout)
    assert faults < 0.05 * pages, (faults, pages)


BLOCKS = """
import resource, sys
import numpy as np
from isolume.app.allocator import for_pictures, tune_malloc
tune_malloc()
if sys.argv[1] == "pictures":
    for_pictures()
faults = []
for i in range(60):  # a 4 MiB block, made, written and freed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.ones(1 << 19)
    del block
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[10:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_pictures_keep_their_blocks_of_a_few_megabytes_where_a_bake_maps_them_alone():
    """While a command draws pictures (`for_pictures`) it keeps its blocks of a few
    megabytes in its heap (no fault when the next one is written), where a bake's are
    mapped alone and fault in again each time (at least one fault per block: 2 MiB pages
    at the most)."""
    def faults(mode: str) -> int:
        return int(subprocess.run([sys.executable, "-c", BLOCKS, mode], check=True,
                                  capture_output=True, text=True).stdout)

    assert faults("pictures") < 10
    assert faults("bake") >= 50


@pytest.mark.parametrize("words", [
    ["render", "synthetic:sphere:24", "--size", "32x32", "--samples", "4"],
    ["movie", "synthetic:sphere:24", "--size", "32x32", "--samples", "4", "--frames", "2"],
])
def test_the_picture_commands_keep_their_blocks_before_they_draw(tmp_path, monkeypatch, words):
    """``render`` and ``movie`` switch to `for_pictures` once, before their pictures."""
    from isolume.app import allocator
    from isolume.app.cli import main

    calls = []
    monkeypatch.setattr(allocator, "for_pictures", lambda: calls.append(True))
    out = str(tmp_path / "p.png") if words[0] == "render" else f"{tmp_path}/frames/"
    assert main([*words, "--out", out]) == 0
    assert calls == [True]
