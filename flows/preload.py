"""Import the heavy libraries in a worker process before it runs or unpickles any task.

A Dask worker unpickles its next task on its event-loop thread while the previous one runs on
another; if that task was the first to import torch, scipy's array-API check saw a half-imported
`torch` module (`partially initialized module 'torch' has no attribute 'Tensor'`), the worker
died and the run went on with one worker fewer. Dask imports this module (`--preload
embody.flows.preload`) when a worker starts; `flows.runners` passes it to local clusters.
A worker runs several task threads, so its BLAS and torch are single-threaded for its lifetime
(`flows.threads`: concurrent OpenBLAS calls deadlocked; a second torch thread only waits).
Dask's statistical profiler is off: it walks the running task's stack every 10 ms on the
worker's event loop, 6-8 % of a deep-stacked task's CPU on top of the task's own, for a
dashboard profile embody never reads (imported before the worker reads that setting).
"""

from __future__ import annotations

import dask
import scipy.spatial.transform  # noqa: F401  (imports its array-API torch check's helpers)
import torch  # noqa: F401
from threadpoolctl import threadpool_limits

import embody.io  # noqa: F401
import embody.tasks.stages  # noqa: F401

dask.config.set({"distributed.worker.profile.enabled": False})
threadpool_limits(limits=1, user_api="blas")
torch.set_num_threads(1)
try:
    torch.set_num_interop_threads(1)
except RuntimeError:  # inter-op work already started in this process: its pool is fixed
    pass
