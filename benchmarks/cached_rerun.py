"""`embody run` as a user sees it: time to the first line, and a fully cached rerun end to end.

Runs the real command twice in subprocesses on the default synthetic set (`--limit N`) in a
fresh store: the first run computes everything (its wall time is printed too); the second finds
every result in the store, so it must not start Prefect (the summary's `prefect` is false) and
only rewrites the manifest, `sequences.csv` and, when stale, the report.

    python benchmarks/cached_rerun.py [--limit 4] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed_run(args: list[str], cwd: Path) -> tuple[float, float, float, dict]:
    """(seconds to the first stderr line, seconds to exit, CPU seconds, the --json summary).

    CPU seconds (user + system of the child) are printed beside wall time because on a shared
    machine wall time mostly measures the other processes."""
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", "from embody.cli import main; main()", "run", *args,
                             "--json"], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    first = proc.stderr.readline()
    t_first = time.perf_counter() - t0
    out, err = proc.communicate()
    total = time.perf_counter() - t0
    if proc.returncode not in (0, 1):
        raise SystemExit(f"embody run failed ({proc.returncode}):\n{first}{err[-3000:]}")
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    print(f"  first line after {t_first:.2f} s: {first.strip()}", file=sys.stderr)
    return t_first, total, cpu, json.loads(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, default=4)
    parser.add_argument("--out", type=Path, default=None, help="Work folder (default: a temp dir).")
    args = parser.parse_args()
    work = args.out or Path(tempfile.mkdtemp(prefix="embody-cached-"))
    work.mkdir(parents=True, exist_ok=True)
    run_args = ["--limit", str(args.limit), "--store", str(work / "store"), "--name", "bench"]
    print("cold run ...", file=sys.stderr)
    cold_first, cold_s, _, cold = timed_run(run_args, work)
    print("fully cached rerun ...", file=sys.stderr)
    warm_first, warm_s, warm_cpu, warm = timed_run(run_args, work)
    load = os.getloadavg()[0]
    assert not warm["prefect"] and not any(warm["computed"].values()), warm["computed"]
    print(f"RESULT sequences={warm['total']} cold_s={cold_s:.1f} cold_first_line_s={cold_first:.2f} "
          f"cached_rerun_s={warm_s:.2f} cached_rerun_cpu_s={warm_cpu:.2f} "
          f"cached_first_line_s={warm_first:.2f} cached_report_rebuilt="
          f"{warm['report_s'] > 0.5} cached_prefect={warm['prefect']} load_avg={load:.1f}")


if __name__ == "__main__":
    main()
