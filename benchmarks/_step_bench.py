"""What the single-step benchmarks (`metrics_step.py`, `retarget_metrics.py`) share: their
arguments, and the default pipeline's context, shared results and records over the first N
sequences of the default synthetic set in `--store` (kept and reused between runs)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def step_bench(description: str, run: str, n: int) -> tuple[argparse.Namespace, Any, Any,
                                                            dict[str, str], list[dict]]:
    """(args, ctx, pipeline without render, shared keys, new records)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--store", type=Path, required=True, help="Store folder (kept; reused).")
    parser.add_argument("--n", type=int, default=n)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--pstats", type=Path, default=None, help="cProfile of the last repeat.")
    parser.add_argument("--digests", action="store_true", help="Print every array's digest.")
    args = parser.parse_args()

    from embody.config import Config
    from embody.flows.env import configure
    from embody.io import load_dataset
    from embody.synth import default_dataset
    from embody.tasks import stages
    from embody.tasks.execute import new_record, run_shared
    from embody.tasks.pipeline import Context

    store = args.store
    configure(store)
    cfg = Config.model_validate({"run": {"store": str(store), "name": run}})
    refs = list(load_dataset(default_dataset(store / "data")))[: args.n]
    ctx = Context(cfg=cfg, store_root=str(store), run=run)
    pipeline = stages.default_pipeline(critic=cfg.run.critic, render=False)
    ctx.body, ctx.robot, ctx.critic  # noqa: B018  (per-process resources, built before timing)
    shared = {s.name: run_shared(s, ctx, {})["key"] for s in pipeline.shared}
    return args, ctx, pipeline, shared, [new_record(r) for r in refs]
