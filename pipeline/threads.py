"""One BLAS/OpenMP thread per process, set before NumPy loads its libraries.

Imported first by every entry point (the command line; Dask workers get the
same variables through ``distributed.nanny.pre-spawn-environ``; the
benchmarks re-execute themselves with them).  On a busy machine, processes
that each start one BLAS thread per core oversubscribe it many times over.
"""

import os

PINNED = {name: "1" for name in (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")}


def pin():
    """Set the thread variables of this process (and of the processes it starts) to one."""
    os.environ.update(PINNED)
