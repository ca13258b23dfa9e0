"""Task runners for `run.runner`: threads (default), processes, or a Dask cluster."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from embody.config import Config
from embody.config.run import RunConfig

__all__ = ["local_dask_cluster", "make_task_runner"]


def _local_cluster_kwargs(run: RunConfig) -> dict[str, Any]:
    # Workers import torch & co. before any task (see flows/preload.py); a remote cluster's
    # workers need `dask worker ... --preload embody.flows.preload` for the same reason.
    return {"n_workers": run.workers, "threads_per_worker": 1, "processes": True,
            "dashboard_address": ":0", "preload": ["embody.flows.preload"]}


def make_task_runner(run: RunConfig, threads: int | None = None) -> Any:
    """A bounded task runner: Prefect's thread pool is unbounded unless told otherwise;
    `threads` (default `run.workers`) sizes the thread runner's pool (`tasks.workers.task_threads`)."""
    if run.runner == "processes":
        from prefect.task_runners import ProcessPoolTaskRunner
        return ProcessPoolTaskRunner(max_workers=run.workers)
    if run.runner == "dask":
        from prefect_dask import DaskTaskRunner
        if run.dask_address:
            return DaskTaskRunner(address=run.dask_address)
        return DaskTaskRunner(cluster_kwargs=_local_cluster_kwargs(run))
    from prefect.task_runners import ThreadPoolTaskRunner
    return ThreadPoolTaskRunner(max_workers=threads or run.workers)


@contextmanager
def local_dask_cluster(cfg: Config) -> Iterator[Config]:
    """For `--runner dask` without an address: one local cluster for the whole run, and the
    config pointing at it. A run in several flow runs (`flows.chunks`) would otherwise start
    a cluster per chunk beside its parent flow's idle one. Other configs pass through."""
    if cfg.run.runner != "dask" or cfg.run.dask_address:
        yield cfg
        return
    from distributed import LocalCluster

    with LocalCluster(**_local_cluster_kwargs(cfg.run)) as cluster:
        run = cfg.run.model_copy(update={"dask_address": cluster.scheduler_address})
        yield cfg.model_copy(update={"run": run})
