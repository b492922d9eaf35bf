"""Imported first by the command line (`app.cli`), before numpy loads its BLAS: every BLAS
and OpenMP library starts with one thread (`THREAD_VARIABLES`, where the environment does
not set them), and `volumes.cores.use` grows those loaded to the command's ``--workers``.
A BLAS loaded with more threads starts them at once, and each spins for ~0.1 s as it
starts: on cores that a ``--workers 1`` command does not hold, in the first stage of its
timeline. isolume's own work runs on its pool, not in BLAS: a BLAS loaded later (SciPy's,
for the suggested isovalues) keeps its one thread."""

import os

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""What a BLAS or OpenMP library reads, as it loads, for the threads it starts."""

for _name in THREAD_VARIABLES:
    os.environ.setdefault(_name, "1")
