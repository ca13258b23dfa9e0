"""`run` and `debug`: dataset-level orchestration settings (never part of a content key)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from embody.config.base import Section


class RunConfig(Section):
    #: Artifact store directory (local filesystem); `embody run --store` overrides it.
    store: str = Field("embody-store", min_length=1)
    #: Run name (manifest `runs/<name>/`); default derived from the dataset and split.
    name: str | None = Field(None, min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    workers: int = Field(2, ge=1, le=256)
    runner: Literal["threads", "processes", "dask"] = "threads"
    #: With the thread runner and several workers, each worker thread computes in a process of
    #: its own, forked from one warmed process (`embody.tasks.workers`), so the workers never
    #: share a GIL; false computes in the threads.
    worker_processes: bool = True
    dask_address: str | None = None
    #: Sequences per task submission: 20k sequences become 20k/batch_size task runs per step.
    batch_size: int = Field(8, ge=1, le=10_000)
    #: Most task runs one Prefect flow run holds: a run that needs more runs its batches in
    #: consecutive subflow runs ("chunks") of at most this many (Prefect stalls and leaks
    #: past about a thousand task runs per flow run on Dask and Ray).
    max_task_runs: int = Field(1000, ge=8, le=100_000)
    limit: int | None = Field(None, ge=1)
    #: Skip the first N sequences (before `limit`): with `limit`, a window of the dataset, so
    #: several drivers can split one dataset under one run name (their manifests merge).
    offset: int = Field(0, ge=0)
    #: Run the critic refinement step after IK (`embody run --critic none` skips it).
    critic: bool = True
    #: Render each sequence's comparison sheet (and `render.preview_format` preview) into the store.
    render: bool = True
    #: Build the report (`embody.report`) at the end of the run; `embody report` builds it later.
    report: bool = True
    seed: int = 0
    synth_n: int = Field(24, ge=1)


class DebugConfig(Section):
    #: Sequence ids that raise on purpose: used to test failure isolation and resume.
    fail_on: list[str] = []
    #: The step at which `fail_on` sequences raise.
    fail_step: str = Field("collide", min_length=1)
