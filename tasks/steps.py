"""Thin Prefect tasks around `tasks.execute`: one task name per step, batches as task runs.

The store is the cache, so Prefect's own caching and result persistence are off: results are
small records (keys, metrics, status) and the default cache policy (which includes the run id)
would never hit across runs anyway.
"""

from __future__ import annotations

from typing import Any

from prefect import Task, task
from prefect.cache_policies import NO_CACHE

from embody.tasks import workers
from embody.tasks.pipeline import Context, Step

__all__ = ["batch_task", "shared_task"]

_OPTIONS = dict(persist_result=False, cache_policy=NO_CACHE, retries=0, log_prints=False)


@task(name="step", **_OPTIONS)
def _batch(step: Step, ctx: Context, records: list[dict[str, Any]],
           shared: dict[str, str]) -> list[dict[str, Any]]:
    return workers.batch(step, ctx, records, shared)


@task(name="shared-step", **_OPTIONS)
def _shared(step: Step, ctx: Context, shared: dict[str, str]) -> dict[str, Any]:
    return workers.shared(step, ctx, shared)


def batch_task(step: Step, batch: int) -> Task:
    """The task of `step` for batch number `batch` (named so the UI shows step and batch)."""
    return _batch.with_options(name=step.name, task_run_name=f"{step.name}[{batch}]")


def shared_task(step: Step) -> Task:
    return _shared.with_options(name=step.name, task_run_name=step.name)
