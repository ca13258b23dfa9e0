"""Whole-pipeline benchmark: the default run, cold, with per-step seconds per sequence.

Runs the default flow (every step `embody run` runs: collide, shape fit, retarget, refine with the
geometric critic, render, metrics, physics) over the default synthetic set in a fresh store, then reads the
store's computation log for each step's compute time. `seconds_per_seq` is the flow's wall time
(report build excluded, printed separately) divided by the number of sequences; the per-step
figures are the summed compute seconds of that step divided by the same number, so with N workers
they add up to about N × seconds_per_seq; `<step>_cpu_s` is the CPU time of the worker thread
that computed it (recorded by `tasks.execute`; GL raster threads and the x264 child excluded),
and `outside_steps_s` the worker-seconds spent outside any step's computation (Prefect task
runs, store reads/writes, the driver, workers idle at the tail). `cpu_s_per_seq` (this process, its finished
children and its worker processes, `embody.tasks.workers`) and the load average at the end are printed too: on a shared machine compare runs made
back to back or side by side, never against a figure from another day. Where the CPU outside
the steps goes: `driver_cpu_s_per_seq` (this process alone: Prefect, the flow's driver, the
report's own work), `report_cpu_s_per_seq` (the report, its helper processes included),
`worker_cpu_s_per_seq` (the worker processes, as they report at the run's end, their x264
children and GL raster threads included) and `worker_outside_cpu_s_per_seq` (that less the
steps' thread CPU: store reads and publishes, pickles, raster threads, x264). The store is new, so
Prefect's database is too: it is copied from the machine's migrated template when there is one
(`prefect_db=seeded`, `flows/ephemeral.py`), else migrated (`prefect_db=migrated`, ~4.8 s more).

    python benchmarks/pipeline.py [--limit N] [--workers 2] [--runner threads]
                                [--worker-processes on|off] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path

STEPS = ("collide", "retarget", "refine", "render", "metrics", "physics")


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _own_cpu() -> tuple[float, float]:
    """(this process's CPU seconds, its finished children's)."""
    t = os.times()
    return t.user + t.system, t.children_user + t.children_system


def _time_report(into: list[float]) -> None:
    """Wrap the flow's report build so its CPU seconds (its helper processes' included) are
    added to `into`: the run's CPU figure holds them, its wall figure does not."""
    import embody.flows.dataset as dataset
    build = dataset.build_report

    def timed(*args, **kwargs):
        c0 = sum(_own_cpu())
        try:
            return build(*args, **kwargs)
        finally:
            into.append(sum(_own_cpu()) - c0)
    dataset.build_report = timed


def _server_cpu() -> float:
    """CPU seconds of this process's Prefect server child so far (Linux; 0 without one): it
    shares the cores with the workers but is not in `cpu_s_per_seq` (a child still running)."""
    from embody.flows.ephemeral import running_server
    from embody.tasks.workers import process_cpu_seconds
    server = running_server()
    return 0.0 if server is None or server.proc is None else process_cpu_seconds(server.proc.pid)


def _prefect_db() -> str:
    """How the run's Prefect database began: copied from the migrated template (`seeded`), or
    migrated by the server (`migrated`, a machine's first run; it then saves the template)."""
    from embody.flows.ephemeral import running_server
    server = running_server()
    return "external" if server is None else ("seeded" if server.seeded else "migrated")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, default=None, help="Only the first N sequences.")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--runner", default="threads", choices=("threads", "processes", "dask"))
    parser.add_argument("--worker-processes", choices=("on", "off"), default="on",
                        help="run.worker_processes: the thread runner's workers compute in "
                             "processes of their own (default) or in the threads.")
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
    from embody.tasks import workers
    from embody.tasks.workers import cpu_seconds as worker_cpu

    configure(store_dir)
    data = default_dataset(store_dir / "data")
    cfg = Config.model_validate({"run": {"store": str(store_dir), "workers": args.workers,
                                         "runner": args.runner, "limit": args.limit,
                                         "worker_processes": args.worker_processes == "on",
                                         "name": "bench-pipeline"}})
    report_cpu: list[float] = []
    _time_report(report_cpu)
    own0, pool0 = _own_cpu()[0], workers._CPU[0]
    t0, c0, epoch0 = time.perf_counter(), _cpu() + worker_cpu(), time.time()
    summary = run_flow(data, cfg)
    wall = time.perf_counter() - t0 - summary["report_s"]
    cpu = _cpu() + worker_cpu() - c0  # the worker processes' CPU included
    driver_cpu = _own_cpu()[0] - own0
    pool_cpu = workers._CPU[0] - pool0  # the worker processes (the zygote's not included)
    server_cpu = _server_cpu()  # its boot included: it started inside run_flow
    n = summary["ok"] + summary["failed"]
    per_step: dict[str, float] = defaultdict(float)
    cpu_step: dict[str, float] = defaultdict(float)
    rows = ArtifactStore(store_dir).computations()
    # the flow's start to its first step computation: server boot, warm-up, Prefect's first calls
    startup = min((r["time"] - float(r.get("compute_s", 0.0)) for r in rows), default=epoch0)
    startup -= epoch0
    for row in rows:
        per_step[row["step"]] += float(row.get("compute_s", 0.0))
        cpu_step[row["step"]] += float(row.get("cpu_s", 0.0))
    # what the workers spent outside step computations: Prefect task runs, store reads and
    # writes, the driver, idle workers at the tail (all worker-seconds not in a compute_s)
    overhead = args.workers * wall - sum(per_step.values())
    m = max(n, 1)
    step_cpu = sum(cpu_step.values())
    print(f"sequences={n} ok={summary['ok']} failed={summary['failed']} workers={args.workers} "
          f"flow_s={wall:.1f} report_s={summary['report_s']:.1f} prefect_db={_prefect_db()}")
    print("  step        wall s total  wall s/seq  worker-thread CPU s/seq")
    for step, secs in sorted(per_step.items()):
        print(f"  {step:10s} {secs:10.2f} {secs / m:10.2f} {cpu_step[step] / m:10.2f}")
    print(f"  outside steps (worker-seconds) {overhead:.1f} total, {overhead / m:.2f} s/seq; "
          f"first step computation {startup:.1f} s after the flow's start")
    print("RESULT " + " ".join([f"seconds_per_seq={wall / m:.2f}"]
                               + [f"{s}_s={per_step.get(s, 0.0) / m:.2f}" for s in STEPS]
                               + [f"{s}_cpu_s={cpu_step.get(s, 0.0) / m:.2f}" for s in STEPS]
                               + [f"outside_steps_s={overhead / m:.2f}",
                                  f"startup_s={startup:.1f}",
                                  f"cpu_s_per_seq={cpu / m:.2f}",
                                  f"server_cpu_s_per_seq={server_cpu / m:.2f}",
                                  f"driver_cpu_s_per_seq={driver_cpu / m:.2f}",
                                  f"report_cpu_s_per_seq={sum(report_cpu) / m:.2f}",
                                  *([f"worker_cpu_s_per_seq={pool_cpu / m:.2f}",
                                     f"worker_outside_cpu_s_per_seq={(pool_cpu - step_cpu) / m:.2f}"]
                                    if pool_cpu > 0 else []),  # no worker processes: threads
                                  f"load1={os.getloadavg()[0]:.1f}"]))


if __name__ == "__main__":
    main()
