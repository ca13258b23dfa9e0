"""`run` and `debug`: dataset-level orchestration settings."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from embody.config.base import Section


class RunConfig(Section):
    workers: int = Field(2, ge=1, le=256)
    runner: Literal["threads", "processes", "dask"] = "threads"
    dask_address: str | None = None
    limit: int | None = Field(None, ge=1)
    seed: int = 0
    synth_n: int = Field(24, ge=1)


class DebugConfig(Section):
    #: Sequence ids that raise on purpose: used to test failure isolation and resume.
    fail_on: list[str] = []
