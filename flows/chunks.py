"""Bounded task runs per flow run: a big run's batches go through consecutive subflow runs.

Prefect's flow runs stall or leak past about a thousand task runs on Dask and Ray (Prefect
#12877, prefect-ray #76, #21697), and every task run of a flow run is one more row its server
writes under that flow run. The driver submits one task run per (step, batch) plus one per
shared step, so a run of B batches through S per-sequence steps needs up to S·B + shared task
runs. `plan_chunks` cuts the batches into chunks that each stay within `run.max_task_runs`;
`run_chunks` runs each chunk as a subflow run ("<run> chunk i/n", one after the other, under
the run's flow run) with a fresh task runner, while one driver carries the shared results,
manifest and counts across them. A run that fits in one chunk runs in its own flow run as
before. The tail split of batches (`flows.dataset._Driver._split`) is held to the same bound.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ["plan_chunks", "run_chunks"]


def plan_chunks(batches: list[list[dict[str, Any]]], steps: int, shared: int,
                max_task_runs: int) -> list[list[list[dict[str, Any]]]]:
    """Consecutive chunks of `batches`, each needing at most `max_task_runs` task runs
    (`steps` per batch; the first chunk also runs the `shared` steps). At least one batch per
    chunk, whatever the bound."""
    per_chunk = max(1, max_task_runs // max(1, steps))
    first = max(1, (max_task_runs - shared) // max(1, steps))
    chunks = [batches[:first]]
    chunks += [batches[i:i + per_chunk] for i in range(first, len(batches), per_chunk)]
    return [c for c in chunks if c] or [[]]


def run_chunks(run: str, chunks: list[list[list[dict[str, Any]]]],
               drive: Callable[[list[list[dict[str, Any]]]], None],
               task_runner: Callable[[], Any]) -> None:
    """`drive(chunk)` inside one subflow run per chunk, each with `task_runner()`'s runner.

    Called inside the run's own flow, so each chunk is a child flow run of it; the subflow
    takes no parameters (the driver stays in this process: nothing large is serialized)."""
    from prefect import flow

    def body_of(chunk: list[list[dict[str, Any]]]) -> Callable[[], None]:
        def body() -> None:
            drive(chunk)
        return body

    for i, chunk in enumerate(chunks):
        sub = flow(name="embody-chunk", flow_run_name=f"{run} chunk {i + 1}/{len(chunks)}",
                   persist_result=False, log_prints=False, validate_parameters=False,
                   task_runner=task_runner())(body_of(chunk))
        sub()
