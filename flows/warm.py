"""A fully cached run without Prefect: when the store already holds every result, say so fast.

Starting Prefect's ephemeral server takes seconds, and a warm rerun submits no task anyway
(the flow's driver resolves store hits itself). So `embody run` first asks the store, with the
same keys and the same `tasks.execute.cached` the driver uses, whether every step of every
sequence is a hit. If so, the manifest, `sequences.csv` and the report are written here and
no Prefect server is started; otherwise the caller runs the flow as usual.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from embody.config import Config
from embody.flows.progress import Progress
from embody.store import ArtifactStore
from embody.tasks.execute import cached, new_record
from embody.tasks.pipeline import Context

__all__ = ["run_cached"]


def run_cached(dataset: str | Path, cfg: Config, *, split: str | None = None,
               progress: bool = False, run: str | None = None) -> dict[str, Any] | None:
    """The run's summary when every result is already stored (nothing computed), else None.

    `run` is the run name the flow would use (default: `cfg.run.name`, else the dataset stem).
    """
    from embody.io import load_dataset
    from embody.tasks.stages import default_pipeline

    t0 = time.perf_counter()
    store = ArtifactStore(cfg.run.store)
    if cfg.debug.fail_on:  # injected failures are exercised by the flow
        return None
    refs = list(load_dataset(dataset, split, cfg.io))[cfg.run.offset:]
    refs = refs[: cfg.run.limit] if cfg.run.limit else refs
    # The flow module's helpers (names, tables, report): importing Prefect is cheap next to
    # starting its server, which is what this path avoids.
    from embody.flows import dataset as flow_module
    if run is None:
        run = flow_module.run_name(cfg, dataset, split)
    pipeline = default_pipeline(critic=cfg.run.critic, render=cfg.run.render)
    ctx = Context(cfg=cfg, store_root=str(store.root), run=run)
    shared: dict[str, str] = {}
    for step in pipeline.shared:
        key = ctx.key(step, {s.name: shared[s.name] for s in step.inputs})
        if not (store.has(step.name, key) and store.intact(step.name, key)):
            return None
        shared[step.name] = key
    records = [new_record(r) for r in refs]
    for step in pipeline.per_sequence:
        hits = cached(step, ctx, records, shared)
        if hits is None:
            return None
        records = hits
    # Every result is stored: record the run exactly as the flow would have (same bookkeeping).
    manifest = flow_module.start_manifest(store, run, refs, dataset, split, pipeline, cfg)
    for name, key in shared.items():
        manifest.set_shared(name, key)
    bar = Progress([s.name for s in pipeline.per_sequence], len(refs), enabled=progress)
    for step in pipeline.per_sequence:
        bar.add(step.name, done=len(records), cached=len(records))
    for rec in records:
        manifest.update(rec)
        manifest.finish_sequence(rec["id"])
    return flow_module.finish_run(
        store, run, manifest, cfg, dataset=dataset, split=split, t0=t0,
        computed={s.name: 0 for s in pipeline.per_sequence + pipeline.shared},
        shared=dict(shared), prefect=False)
