"""Collision mitigation on the default synthetic dataset: the shipped default vs the paper preset.

Prints one row per sequence, Table I of each setting, the paper preset's RESULT-style line, and
ends with the default preset's `RESULT` line. `--paper-n` bounds the paper preset's sequences
(it runs 500 steps each; 0 skips it). Runtime is wall-clock per sequence (it includes the mesh
depth measure before/after); `cpu_s` is this process's CPU time (robust to other load on the
machine). `seconds_per_150_frames` leaves the mesh-depth judge out (its `depth_s` is
kept apart by `mitigate`); `total_seconds_per_150_frames` adds it back, and
`cpu_seconds_per_150_frames` is the whole call's CPU time. The RESULT line adds the mesh penetration depth (`embody.collision.depth`, every
vertex): frames deeper than 5 mm before/after and the max depth after, on the default set, and
the same plus Pose MSE / ΔAccel / the unchanged-far-frames check (`long_*`) on one long
real-like sequence with sparse collisions (`--long-n` synthetic sequences' clear stretches and
two colliding windows, cross-faded; 0 skips it). Before any timed run, `mitigate` runs once
untimed on a short colliding window of the first sequence (`warm_up`): a fresh process loads
the compiled kernels from numba's cache (0.6-0.8 s, once per process), a start-up cost that
would otherwise land on the first timed sequence, not a per-150-frame one; the judge's memo is
cleared after it, so no timed run reuses its judged frames. `--sweep` first prints one row
per closeness weight and clearance in `SWEEP` (how the default was picked; see `embody.config.collision`).

    python benchmarks/collision.py [--data DIR] [--n 24] [--paper-n 6] [--long-n 8] [--sweep]
        [--solver gauss_newton] [--set lambda_col=300 ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from embody.body import MannequinBody
from embody.collision import depth, mitigate, part_volumes
from embody.collision.energy import collision_model, frame_energies
from embody.collision.metrics import table1
from embody.collision.optimize import blend_weights
from embody.motion import Motion
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
              f"cpu={m['cpu_s']:.2f}s depth_mm {m.get('max_depth_mm_before', 0):.1f} -> "
              f"{m.get('max_depth_mm_after', 0):.2f} (>5mm {m.get('frames_over_5mm_before', 0)}"
              f" -> {m.get('frames_over_5mm_after', 0)}) depth_s={m.get('depth_s', 0):.1f}",
              flush=True)
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
            f"seconds_per_150_frames_1thread={per150:.2f} "
            f"cpu_seconds_per_seq_mean={df['cpu_s'].mean():.2f} "
            f"cpu_seconds_per_150_frames={(df['cpu_s'] / df['frames'] * 150).mean():.2f} "
            + (f"total_seconds_per_150_frames="
               f"{((df['runtime_s'] + df['depth_s']) / df['frames'] * 150).mean():.2f} "
               if "depth_s" in df else "") +
            f"frames={int(df['frames'].sum())}"
            + (f" frames_over_5mm_before={int(df['frames_over_5mm_before'].sum())}"
               f" frames_over_5mm_after={int(df['frames_over_5mm_after'].sum())}"
               f" frames_over_2mm_after={int(df['frames_over_2mm_after'].sum())}"
               f" max_depth_mm_before={df['max_depth_mm_before'].max():.1f}"
               f" max_depth_mm_after={df['max_depth_mm_after'].max():.2f}"
               f" depth_check_seconds_per_seq_mean={df['depth_s'].mean():.2f}"
               if "max_depth_mm_after" in df else ""))


def _clear_runs(e: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of runs of zero energy."""
    runs, start = [], None
    for i, v in enumerate(np.r_[e, 1.0]):
        if v == 0 and start is None:
            start = i
        elif v != 0 and start is not None:
            runs.append((start, i))
            start = None
    return runs


def _stride_energies(m: Motion, body, cfg: CollisionConfig) -> np.ndarray:
    """Per-frame collision energy on the `vertex_stride` subsample (the paper's measure)."""
    model = collision_model(body, m.betas, vertex_stride=cfg.vertex_stride)
    with torch.no_grad():
        return frame_energies(model, body.joint_transforms(
            torch.as_tensor(m.pose, dtype=torch.float32),
            torch.as_tensor(m.betas, dtype=torch.float32)), cfg.tolerance).numpy()


def warm_up(path: Path, body, cfg: CollisionConfig, frames: int = 30) -> None:
    """Run `mitigate` once, untimed, on `frames` frames around the first sequence's most
    colliding one: loads the compiled kernels (numba's cache) before any timed run."""
    m = load(path)
    e = _stride_energies(m, body, cfg)
    a = max(0, min(int(np.argmax(e)) - frames // 2, len(m.pose) - frames))
    mitigate(Motion(pose=m.pose[a:a + frames], transl=m.transl[a:a + frames], betas=m.betas,
                    fps=m.fps), body, cfg)
    depth._memo.clear()  # timed runs judge their own frames


def long_sequence(paths: list[Path], body, cfg: CollisionConfig, fade: int = 8) -> Motion:
    """A long real-like sequence with sparse collisions: each sequence's longest clear stretch
    (stride-8 energy 0), and a 20-frame colliding window from the first two, cross-faded."""
    pieces = []
    for i, p in enumerate(paths):
        m = load(p)
        e = _stride_energies(m, body, cfg)
        runs = _clear_runs(e)
        if runs:
            a, b = max(runs, key=lambda r: r[1] - r[0])
            pieces.append(m.pose[a:b])
        if i < 2 and (e > 0).any():
            c = int(np.argmax(e))
            pieces.append(m.pose[max(0, c - 10):c + 10])
    out = pieces[0]
    for nxt in pieces[1:]:
        w = np.linspace(0.0, 1.0, fade + 2)[1:-1, None, None]
        out = np.concatenate([out, (1 - w) * out[-1] + w * nxt[0], nxt])
    first = load(paths[0])
    return Motion(pose=out, transl=np.zeros((len(out), 3)), betas=first.betas, fps=first.fps)


def long_result(motion: Motion, body, cfg: CollisionConfig) -> str:
    from embody.collision.energy import collision_model as cm
    t = time.perf_counter()
    r = mitigate(motion, body, cfg)
    wall = time.perf_counter() - t
    m = r.metrics
    fine = cm(body, motion.betas, vertex_stride=cfg.contact_stride)
    with torch.no_grad():
        e = frame_energies(fine, body.joint_transforms(
            torch.as_tensor(motion.pose, dtype=torch.float32),
            torch.as_tensor(motion.betas, dtype=torch.float32)), cfg.tolerance).numpy()
    far = blend_weights(e > 0, int(round(cfg.blend_s * motion.fps))) == 0
    same = bool((r.motion.pose[far] == motion.pose[far]).all())
    return (f"long_frames={m['frames']} long_penetrating_frames_before={int((e > 0).sum())} "
            f"long_frames_over_5mm_before={m['frames_over_5mm_before']} "
            f"long_frames_over_5mm_after={m['frames_over_5mm_after']} "
            f"long_max_depth_mm_after={m['max_depth_mm_after']:.2f} "
            f"long_pose_mse={m['pose_mse']:.4f} long_daccel={m['daccel_mse']:+.3e} "
            f"long_far_frames={int(far.sum())} long_far_unchanged={same} "
            f"long_seconds={wall:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--paper-n", type=int, default=6)
    ap.add_argument("--long-n", type=int, default=8)
    ap.add_argument("--sweep", action="store_true", help="first print the SWEEP rows")
    ap.add_argument("--solver", choices=("adam", "gauss_newton"), default=None,
                    help="override collision.solver (default: the config's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a collision config field (YAML value), repeatable")
    args = ap.parse_args()
    torch.set_num_threads(1)
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))[: args.n]
    body = MannequinBody()
    t = time.perf_counter()
    part_volumes(body)
    print(f"part volumes ready in {time.perf_counter() - t:.1f}s (cached after the first run)")
    over = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    if args.solver is not None:
        over["solver"] = args.solver
    default = CollisionConfig.model_validate({**CollisionConfig().model_dump(), **over})
    t = time.perf_counter()
    warm_up(paths[0], body, default)
    print(f"warm-up (compiled kernels loaded) in {time.perf_counter() - t:.1f}s, untimed")
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
    long = ""
    if args.long_n:
        motion = long_sequence(paths[: args.long_n], body, default)
        long = " " + long_result(motion, body, default)
        print(f"long sequence:{long}", flush=True)
    if args.paper_n:
        df_paper = run("paper", paper, paths[: args.paper_n], body)
    df_default = run("default", default, paths, body)
    with pd.option_context("display.width", 200):
        if args.paper_n:
            print("\nTable I, paper preset\n", table1(df_paper))
        print("\nTable I, default preset\n", table1(df_default))
    if args.paper_n:
        print(f"\npaper preset: {result_line(df_paper)}")
    print(f"RESULT {result_line(df_default)}{long}")


if __name__ == "__main__":
    main()
