"""The BLAS thread count of the solvers' processes.

The fast SQP and the estimators call BLAS (NumPy's and SciPy's OpenBLAS) on small matrices
(a 60 x 60 Hessian at N = 30) thousands of times per solve. Left at its default, OpenBLAS
starts one thread per core for each call, and on a busy machine those threads wait for each
other: one N = 30 solve spent 65% of its time in ``numpy.linalg.eigh`` (136 ms a call against
~1.6 ms at one thread). So the solvers set the count themselves, process-wide, when one is
built (:func:`controllers.solvers.make_solver`) and when an evaluation task starts in any
worker (serial, pool, Dask): :func:`limit_blas_threads`.

The count is :data:`DEFAULT_BLAS_THREADS` (1) unless the environment variable
:data:`BLAS_THREADS_ENV` (``LFM_BLAS_THREADS``) says otherwise: a positive integer, or
``none`` to leave BLAS as it is (e.g. a user who sets ``threadpoolctl`` limits of their own).
``OPENBLAS_NUM_THREADS`` and ``OMP_NUM_THREADS`` no longer matter for the solvers.
"""

from __future__ import annotations

import os
from typing import Any

#: The environment variable that overrides the solvers' BLAS thread count.
BLAS_THREADS_ENV = "LFM_BLAS_THREADS"
#: The BLAS threads of the solvers' processes unless :data:`BLAS_THREADS_ENV` is set.
DEFAULT_BLAS_THREADS = 1
_LARGEST = 1024  # more threads than this is surely a typo

# (pid, count) of the limit applied in this process; a forked child applies it again.
_applied: tuple[int, int | None] | None = None


def blas_threads(environ: Any = None) -> int | None:
    """The BLAS thread count to apply: ``LFM_BLAS_THREADS`` or :data:`DEFAULT_BLAS_THREADS`;
    ``None`` when the variable says ``none`` (leave BLAS alone).

    Raises:
        ValueError: naming the variable, for anything but an integer in [1, 1024] or ``none``.
    """
    env = os.environ if environ is None else environ
    text = str(env.get(BLAS_THREADS_ENV, "")).strip()
    if not text:
        return DEFAULT_BLAS_THREADS
    if text.lower() == "none":
        return None
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= _LARGEST:
        raise ValueError(
            f"{BLAS_THREADS_ENV}={text!r}: must be an integer in [1, {_LARGEST}] (BLAS threads "
            "of the solvers' processes) or 'none' (leave BLAS as it is)"
        )
    return value


def limit_blas_threads(threads: int | None = None) -> int | None:
    """Set the BLAS libraries loaded in this process to ``threads`` threads (default:
    :func:`blas_threads`), once per process and count; later calls cost a dict lookup.

    NumPy's and SciPy's BLAS are loaded first, so that both are limited. Returns the count
    applied (``None``: BLAS left alone).
    """
    global _applied
    count = blas_threads() if threads is None else int(threads)
    key = (os.getpid(), count)
    if _applied == key:
        return count
    if count is not None:
        import numpy  # noqa: F401  (its BLAS)
        import scipy.linalg  # noqa: F401  (SciPy's own BLAS)
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=count, user_api="blas")
    _applied = key
    return count


def blas_thread_counts() -> list[int]:
    """The thread count of every BLAS library loaded in this process (threadpoolctl)."""
    from threadpoolctl import threadpool_info

    return [int(i["num_threads"]) for i in threadpool_info() if i.get("user_api") == "blas"]


__all__ = [
    "BLAS_THREADS_ENV",
    "DEFAULT_BLAS_THREADS",
    "blas_thread_counts",
    "blas_threads",
    "limit_blas_threads",
]
