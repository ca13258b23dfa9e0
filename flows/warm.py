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
from embody.flows.verdicts import verdict_summary
from embody.store import ArtifactStore, Manifest
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
    # Every result is stored: record the run exactly as the flow would have.
    manifest = Manifest(store, run)
    manifest.start([r.id for r in refs], dataset=str(Path(dataset).expanduser().resolve()), split=split,
                   steps=pipeline.names, config=cfg.model_dump(mode="json"))
    for name, key in shared.items():
        manifest.set_shared(name, key)
    bar = Progress([s.name for s in pipeline.per_sequence], len(refs), enabled=progress)
    for step in pipeline.per_sequence:
        bar.add(step.name, done=len(records), cached=len(records))
    for rec in records:
        manifest.update(rec)
        manifest.finish_sequence(rec["id"])
    manifest.save(finished=True)
    table = flow_module.write_tables(store, run)
    t_report = time.perf_counter()
    report, report_error = (flow_module.build_report(store, run) if cfg.run.report
                            else (None, None))
    report_s = time.perf_counter() - t_report
    return {"run": run, "store": str(store.root), "dataset": str(dataset), "split": split,
            "total": len(records), "ok": len(records), "failed": 0, "failures": [],
            "computed": {s.name: 0 for s in pipeline.per_sequence + pipeline.shared},
            "shared": dict(shared), "manifest": str(manifest.path), "table": str(table),
            "report": report, "report_error": report_error, "report_s": round(report_s, 3),
            "elapsed_s": round(time.perf_counter() - t0, 3), "prefect": False,
            **verdict_summary(manifest)}
