"""Report and export cost on a finished run: collect (store → RunData), write (tables, figures,
page) and the trajectory-library export.

    python benchmarks/report.py [--store embody-store] [--run NAME]

Prints one row per sequence, then the phase timings, and ends with
`RESULT collect_s=… write_s=… export_s=… sequences=… per_seq_ms=… exported=… excluded=…`.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

from embody.report import collect, latest_run, write_report
from embody.export.runs import run_trajectories
from embody.report.reader import open_run, run_config
from embody.export.library import export_library


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", default="embody-store")
    parser.add_argument("--run", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if not Path(args.store, "runs").is_dir():
        print(f"no runs in {args.store}: run `embody run --store {args.store}` first", file=sys.stderr)
        return 2
    run = args.run or latest_run(args.store)
    robot = run_config(open_run(args.store, run)[1]).robot.name

    t0 = time.perf_counter()
    data = collect(args.store, run)
    t1 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        write_report(data, Path(tmp) / "report")
        t2 = time.perf_counter()
        trajectories, failed = run_trajectories(args.store, run, robot)
        library, excluded = export_library(trajectories, Path(tmp) / "library", "npz", failed)
        t3 = time.perf_counter()
    seqs = data.per_sequence().set_index("id")
    print(f"{'sequence':<24} {'status':<7} {'reduction_%':>11} {'wrist_mm':>9}  export")
    for sid, row in seqs.iterrows():
        wrist = row.get("refine.wrist_mm_mean", row.get("retarget.wrist_pos_err_mm"))
        state = "ok" if sid in set(library["id"]) else "excluded"
        print(f"{sid:<24} {row['status']:<7} {row.get('collide.reduction_pct', float('nan')):>11.2f}"
              f" {wrist:>9.1f}  {state}")
    n = len(seqs)
    print(f"collect {t1 - t0:.2f} s, write {t2 - t1:.2f} s, export {t3 - t2:.2f} s")
    print(f"RESULT collect_s={t1 - t0:.2f} write_s={t2 - t1:.2f} export_s={t3 - t2:.2f} "
          f"sequences={n} per_seq_ms={1000 * (t3 - t0) / max(n, 1):.0f} "
          f"exported={len(library)} excluded={len(excluded)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
