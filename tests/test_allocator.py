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
from isolume.app.allocator import mapped_block, tune_malloc
tune_malloc(mapped_block(sys.argv[1]))
faults = []
for i in range(60):  # a 4 MiB block, made, written and freed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.ones(1 << 19)
    del block
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[10:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_render_keeps_its_blocks_of_a_few_megabytes_where_a_bake_maps_them_alone():
    """``render`` makes and frees its blocks of a few megabytes a few times a picture: its
    process keeps them in its heap (no fault when the next one is written), where a bake's
    (and every other command's) are mapped alone and fault in again each time (at least
    one fault per block: 2 MiB pages at the most)."""
    from isolume.app.allocator import MAPPED_BLOCK, RENDER_MAPPED_BLOCK, mapped_block

    assert mapped_block("render") == RENDER_MAPPED_BLOCK > 4 << 20
    assert mapped_block("bake") == mapped_block(None) == MAPPED_BLOCK <= 1 << 20

    def faults(command: str) -> int:
        return int(subprocess.run([sys.executable, "-c", BLOCKS, command], check=True,
                                  capture_output=True, text=True).stdout)

    assert faults("render") < 10
    assert faults("bake") >= 50
