"""One BLAS thread per process: the learner's linear algebra is many small products.

Each learner step is some hundred small matrix products and eigendecompositions (57 x 57
for ErrP features). OpenBLAS spreads even these over its threads, which wait for each
other: on a loaded 2-core machine a T = 25 step measured 270 ms with the default two
threads against 38 ms with one, and ``cfbci simulate --jobs N`` already runs one
session per core. `single_threaded_blas` limits this process to one BLAS thread
and sets the environment so that the processes it starts (simulation workers, services)
start with one. Results do not depend on it (the products are not split along their sums
here), only the time does.
"""

from __future__ import annotations

import os

from threadpoolctl import threadpool_limits

_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas() -> None:
    """Limit this process and its future children to one BLAS thread."""
    limit_blas_threads(1)


def limit_blas_threads(threads: int) -> None:
    """Limit this process and its future children to ``threads`` BLAS threads (>= 1).

    ``cfbci --blas-threads N`` sets it for a whole command: results may then differ from
    one thread's by rounding (a product split over threads sums in another order), which
    is what it is for: measuring how much a session's outcome depends on it.
    """
    if threads < 1:
        raise ValueError(f"--blas-threads must be >= 1; got {threads}")
    for name in _THREAD_VARIABLES:
        os.environ[name] = str(threads)
    threadpool_limits(threads, user_api="blas")
