"""One BLAS and one torch thread per pipeline worker: the run's parallelism is its workers.

NumPy's OpenBLAS (scipy-openblas 0.3.31, pthreads) keeps its own thread pool. With two worker
threads of `embody run` each in a float32 matmul at once (the metrics step's subset skinning),
OpenBLAS deadlocked on 2026-11-26: one thread spinning in `exec_blas`, the other blocked on a
mutex in `sgemm_thread_nt`, the run stalled for good in its metrics step at one core's load.
Torch's intra-op pool does the same harm without the hang: the steps' torch work is many small
ops (the IK's chain FK, the human FK), where a second OpenMP thread per worker only adds barrier
waits (the IK solve of 4 default sequences: 3.4-3.8 CPU-s and 9-10 s wall per sequence with 2
torch threads, 0.30 CPU-s and ~1 s with 1, the same bits; s14-metrics, 2026-11-27). So while a
run has more than one worker, BLAS and torch run single-threaded in its process (`threadpoolctl`,
`embody.device.torch_threads`; the previous settings come back when the run ends). Dask workers get the
same in `flows.preload`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

__all__ = ["worker_threads"]


@contextmanager
def worker_threads(workers: int) -> Iterator[None]:
    """Single-threaded BLAS and torch for a run with `workers` > 1 concurrent workers (else
    unchanged)."""
    if workers <= 1:
        yield
        return
    from embody.device import torch_threads
    with threadpool_limits(limits=1, user_api="blas"), torch_threads(1):
        yield
