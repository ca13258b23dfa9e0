"""Collision mitigation on the default synthetic dataset: the shipped default vs the paper preset.

Prints one row per sequence, Table I of each setting, the paper preset's RESULT-style line, and
ends with the default preset's `RESULT` line. `--paper-n` bounds the paper preset's sequences
(it runs 500 steps each). Runtime is wall-clock per sequence; `cpu_s` is this process's CPU time
(robust to other load on the machine). `--sweep` first prints one row per closeness weight and
clearance in `SWEEP` (how the default was picked; see `embody.config.collision`).

    python benchmarks/collision.py [--data DIR] [--n 24] [--paper-n 6] [--sweep]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pandas as pd
import torch
import yaml

from embody.body import MannequinBody
from embody.collision import mitigate, part_volumes
from embody.collision.metrics import table1
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset

ROOT = Path(__file__).resolve().parents[1]
#: (lambda_close, clearance, early_stop_stall) settings of `--sweep`, on the model defaults.
SWEEP = ((1e-4, 0.0, 40), (0.1, 0.0, 40), (1.0, 0.0, 40), (10.0, 0.0, 40), (10.0, 0.002, 40),
         (10.0, 0.002, 20), (30.0, 0.002, 40))


def run(name: str, cfg: CollisionConfig, paths: list[Path], body,
        quiet: bool = False) -> pd.DataFrame:
    rows = []
    for p in paths:
        motion = load(p)
        cpu = time.process_time()
        m = mitigate(motion, body, cfg).metrics
        m["cpu_s"] = time.process_time() - cpu
        m["seq"] = p.stem
        rows.append(m)
        if quiet:
            continue
        print(f"{name:8s} {p.stem} T={m['frames']:3d} L_col {m['energy_before']:.5f} -> "
              f"{m['energy_after']:.5f} red={m['reduction_pct']:6.2f}% "
              f"pose_mse={m['pose_mse']:.4f} "
              f"daccel={m['daccel_mse']:+.5f} steps={m['steps']:3d} t={m['runtime_s']:.2f}s "
              f"cpu={m['cpu_s']:.2f}s", flush=True)
    return pd.DataFrame(rows)


def result_line(df: pd.DataFrame) -> str:
    c = df[~df["no_collision"]]
    per150 = (df["runtime_s"] / df["frames"] * 150).mean()
    return (f"improved_pct={100.0 * c['improved'].mean():.1f} "
            f"reduction_median_pct={c['reduction_pct'].median():.2f} "
            f"pose_mse_median={c['pose_mse'].median():.4f} "
            f"daccel_median={c['daccel_mse'].median():+.3e} "
            f"seconds_per_seq_mean={df['runtime_s'].mean():.2f} "
            f"seconds_per_150_frames_mean={per150:.2f} "
            f"cpu_seconds_per_seq_mean={df['cpu_s'].mean():.2f} "
            f"frames={int(df['frames'].sum())}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--paper-n", type=int, default=6)
    ap.add_argument("--sweep", action="store_true", help="first print the SWEEP rows")
    args = ap.parse_args()
    torch.set_num_threads(1)
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))[: args.n]
    body = MannequinBody()
    t = time.perf_counter()
    part_volumes(body)
    print(f"part volumes ready in {time.perf_counter() - t:.1f}s (cached after the first run)")
    default = CollisionConfig()
    if args.sweep:
        for close, clearance, stall in SWEEP:
            cfg = CollisionConfig.model_validate({**default.model_dump(), "lambda_close": close,
                                                  "clearance": clearance,
                                                  "early_stop_stall": stall})
            df = run("sweep", cfg, paths, body, quiet=True)
            print(f"sweep lambda_close={close:g} clearance={clearance:g} stall={stall} "
                  f"{result_line(df)}", flush=True)
    # the overlay on the model defaults, so both presets share every other setting
    overlay = yaml.safe_load((ROOT / "configs/collision/paper.yaml").read_text())["collision"]
    paper = CollisionConfig.model_validate({**default.model_dump(), **overlay})
    df_paper = run("paper", paper, paths[: args.paper_n], body)
    df_default = run("default", default, paths, body)
    with pd.option_context("display.width", 200):
        print("\nTable I, paper preset\n", table1(df_paper))
        print("\nTable I, default preset\n", table1(df_default))
    print(f"\npaper preset: {result_line(df_paper)}")
    print(f"RESULT {result_line(df_default)}")


if __name__ == "__main__":
    main()
