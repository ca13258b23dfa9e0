"""One BLAS thread per pipeline worker: the run's parallelism is its workers, not OpenBLAS's.

NumPy's OpenBLAS (scipy-openblas 0.3.31, pthreads) keeps its own thread pool. With two worker
threads of `embody run` each in a float32 matmul at once (the metrics step's subset skinning),
OpenBLAS deadlocked on 2026-11-26: one thread spinning in `exec_blas`, the other blocked on a
mutex in `sgemm_thread_nt`, the run stalled for good in its metrics step at one core's load.
Beyond the hang, N workers × N BLAS threads only oversubscribe the cores. So while a run has
more than one worker, BLAS runs single-threaded in its process (`threadpoolctl`; the previous
setting comes back when the run ends). Dask workers get the same in `flows.preload`.
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

from threadpoolctl import threadpool_limits

__all__ = ["worker_blas"]


def worker_blas(workers: int) -> AbstractContextManager:
    """Single-threaded BLAS for a run with `workers` > 1 concurrent workers (else unchanged)."""
    return threadpool_limits(limits=1, user_api="blas") if workers > 1 else nullcontext()
