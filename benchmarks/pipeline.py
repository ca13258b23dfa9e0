"""Whole-pipeline benchmark: the default run, cold, with per-step seconds per sequence.

Runs the default flow (every step `embody run` runs: collide, shape fit, retarget, refine with the
geometric critic, render, metrics) over the default synthetic set in a fresh store, then reads the
store's computation log for each step's compute time. `seconds_per_seq` is the flow's wall time
(report build excluded, printed separately) divided by the number of sequences; the per-step
figures are the summed compute seconds of that step divided by the same number, so with N workers
they add up to about N × seconds_per_seq. `cpu_s_per_seq` (this process and its finished
children) and the load average at the end are printed too: on a shared machine compare runs made
back to back or side by side, never against a figure from another day.

    python benchmarks/pipeline.py [--limit N] [--workers 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path

STEPS = ("collide", "retarget", "refine", "render", "metrics")


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, default=None, help="Only the first N sequences.")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None, help="Work folder (default: a temp dir).")
    args = parser.parse_args()
    work = args.out or Path(tempfile.mkdtemp(prefix="embody-pipeline-"))
    shutil.rmtree(work / "store", ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    store_dir = work / "store"
    os.chdir(work)  # the run's report goes to ./reports/<run>

    from embody.config import Config
    from embody.synth import default_dataset
    from embody.flows.dataset import run_flow
    from embody.flows.env import configure
    from embody.store import ArtifactStore

    configure(store_dir)
    data = default_dataset(store_dir / "data")
    cfg = Config.model_validate({"run": {"store": str(store_dir), "workers": args.workers,
                                         "limit": args.limit, "name": "bench-pipeline"}})
    t0, c0 = time.perf_counter(), _cpu()
    summary = run_flow(data, cfg)
    wall = time.perf_counter() - t0 - summary["report_s"]
    cpu = _cpu() - c0
    n = summary["ok"] + summary["failed"]
    per_step: dict[str, float] = defaultdict(float)
    for row in ArtifactStore(store_dir).computations():
        per_step[row["step"]] += float(row.get("compute_s", 0.0))
    print(f"sequences={n} ok={summary['ok']} failed={summary['failed']} workers={args.workers} "
          f"flow_s={wall:.1f} report_s={summary['report_s']:.1f}")
    for step, secs in sorted(per_step.items()):
        print(f"  {step:10s} {secs:8.2f} s total  {secs / max(n, 1):6.2f} s/seq")
    print("RESULT " + " ".join([f"seconds_per_seq={wall / max(n, 1):.2f}"]
                               + [f"{s}_s={per_step.get(s, 0.0) / max(n, 1):.2f}" for s in STEPS]
                               + [f"cpu_s_per_seq={cpu / max(n, 1):.2f}",
                                  f"load1={os.getloadavg()[0]:.1f}"]))


if __name__ == "__main__":
    main()
