"""Imported first by the command line (`app.cli`), before numpy loads its BLAS: every BLAS
and OpenMP library starts with one thread (`THREAD_VARIABLES`, where the environment does
not set them), and keeps it: isolume's own work runs on its pool, not in BLAS
(`volumes.cores.use` holds a BLAS to at most ``--workers`` threads and never grows one).
A BLAS loaded with more threads starts them at once, and each spins for ~0.1 s as it
starts — on cores that a ``--workers 1`` command does not hold, and on 16 cores 1.9 s of
CPU in the first stage of a bake. A BLAS loaded later (SciPy's, where a command loads
it) keeps its one thread too.

numba's array maths, loaded as it readies its first kernel, asks SciPy whether a BLAS is
there by importing ``scipy.linalg`` (0.12 s and 30 MB of every command's start, where
nothing else loads it): `numba_without_blas_probe` loads it without that question."""

import os
import sys

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""What a BLAS or OpenMP library reads, as it loads, for the threads it starts."""

for _name in THREAD_VARIABLES:
    os.environ.setdefault(_name, "1")


_PROBED = "scipy.linalg.cython_blas"
"""The module numba's array maths imports to learn whether a BLAS is there."""


def numba_without_blas_probe() -> None:
    """Load numba's array maths (``numba.np.arraymath``) as if SciPy had no BLAS, where
    neither is loaded yet. Its answer only picks how ``np.convolve`` and ``np.correlate``
    multiply inside compiled code (BLAS or a loop); no kernel of isolume calls them, and
    ``np.dot`` or ``np.linalg`` in compiled code still import SciPy's BLAS as they are
    compiled. Call it while no other thread imports (it hides the module for the
    import's ~10 ms): the console script does, before a command that runs kernels starts."""
    if _PROBED in sys.modules or "numba.np.arraymath" in sys.modules:
        return
    sys.modules[_PROBED] = None  # an import of it raises ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules[_PROBED]
