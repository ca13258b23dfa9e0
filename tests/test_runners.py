"""Task runners: a local Dask cluster's workers have the heavy imports done before any task."""

from __future__ import annotations

import sys

from embody.config.run import RunConfig
from embody.flows.runners import make_task_runner


def test_local_dask_workers_preload_torch_before_any_task():
    from distributed import Client, LocalCluster

    runner = make_task_runner(RunConfig(runner="dask", workers=1))
    with LocalCluster(**runner.cluster_kwargs) as cluster, Client(cluster) as client:
        loaded = client.run(lambda: all(m in sys.modules for m in
                                        ("torch", "scipy.spatial.transform", "embody.tasks.stages")))
    assert list(loaded.values()) == [True]
