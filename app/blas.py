"""Imported first by the command line (`app.cli`), before numpy loads its BLAS: every BLAS
and OpenMP library starts with one thread (`THREAD_VARIABLES`, where the environment does
not set them), and keeps it: isolume's own work runs on its pool, not in BLAS
(`volumes.cores.use` holds a BLAS to at most ``--workers`` threads and never grows one).
A BLAS loaded with more threads starts them at once, and each spins for ~0.1 s as it
starts — on cores that a ``--workers 1`` command does not hold, and on 16 cores 1.9 s of
CPU in the first stage of a bake. A BLAS loaded later (SciPy's, for the suggested
isovalues) keeps its one thread too."""

import os

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""What a BLAS or OpenMP library reads, as it loads, for the threads it starts."""

for _name in THREAD_VARIABLES:
    os.environ.setdefault(_name, "1")
