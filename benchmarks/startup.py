"""Start-up of a cold default run: what a run costs before and around its first step.

Runs the default flow (thread runner, `--workers` workers) on a fresh store over the first
`--limit` default sequences with every sequence failing at its collide step (`debug.fail_on`), so
the flow's wall time is its fixed cost: Prefect's ephemeral server start, the flow run, the shared
shape fit, source loading and the run's bookkeeping (the report is off). Prints the seconds from
`run_flow` to the first source computation (`first_task_s`), to the end of the shape fit
(`shape_fit_end_s`), the flow's wall and this process's CPU seconds; on a shared machine compare
checkouts run back to back (`PYTHONPATH=<checkout>`), a few times each.

    python benchmarks/startup.py [--limit 4] [--workers 2] [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--data", type=Path, default=None,
                        help="Where the default synthetic set is (generated there once).")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="embody-startup-"))
    store = work / "store"
    os.chdir(work)

    from embody.flows.env import configure
    configure(store)  # before Prefect is imported
    from embody.config import Config
    from embody.flows.dataset import run_flow
    from embody.io import load_dataset
    from embody.synth import default_dataset

    data = default_dataset(args.data or store / "data")
    ids = [r.id for r in list(load_dataset(data))[: args.limit]]
    cfg = Config.model_validate({"run": {"store": str(store), "workers": args.workers,
                                         "limit": args.limit, "name": "startup", "report": False},
                                 "debug": {"fail_on": ids}})
    t0_epoch, t0, c0 = time.time(), time.perf_counter(), time.process_time()
    summary = run_flow(data, cfg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rows = []
    for f in (store / "counters").glob("*.jsonl"):
        rows += [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
    first = min(r["time"] - r.get("compute_s", 0.0) for r in rows if r["step"] == "source")
    fit = [r["time"] for r in rows if r["step"] == "shape_fit"]
    print(f"sequences={summary['total']} failed={summary['failed']} (every one at collide, on purpose)")
    print(f"RESULT first_task_s={first - t0_epoch:.2f} "
          f"shape_fit_end_s={(fit[0] - t0_epoch) if fit else float('nan'):.2f} flow_s={wall:.2f} "
          f"cpu_s={cpu:.2f} load1={os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
