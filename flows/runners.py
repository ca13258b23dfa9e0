"""Task runners for `run.runner`: threads (default), processes, or a Dask cluster."""

from __future__ import annotations

from typing import Any

from embody.config.run import RunConfig

__all__ = ["make_task_runner"]


def make_task_runner(run: RunConfig) -> Any:
    """A bounded task runner: Prefect's thread pool is unbounded unless told otherwise."""
    if run.runner == "processes":
        from prefect.task_runners import ProcessPoolTaskRunner
        return ProcessPoolTaskRunner(max_workers=run.workers)
    if run.runner == "dask":
        from prefect_dask import DaskTaskRunner
        if run.dask_address:
            return DaskTaskRunner(address=run.dask_address)
        # Workers import torch & co. before any task (see flows/preload.py); a remote cluster's
        # workers need `dask worker ... --preload embody.flows.preload` for the same reason.
        return DaskTaskRunner(cluster_kwargs={"n_workers": run.workers, "threads_per_worker": 1,
                                              "processes": True, "dashboard_address": ":0",
                                              "preload": ["embody.flows.preload"]})
    from prefect.task_runners import ThreadPoolTaskRunner
    return ThreadPoolTaskRunner(max_workers=run.workers)
