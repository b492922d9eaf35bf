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
