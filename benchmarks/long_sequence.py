"""CPU cost per frame of the collide and retarget steps at two lengths: is it linear in length?

A long sequence is synthetic signing clips (`embody.synth.generate_sequence(seed, i)`, 30 fps)
laid end to end, cut to the length. Each (step, length) runs in a fresh subprocess with the
default config (`io.max_frames` raised to fit) and reports its CPU seconds
(`time.process_time`, all threads of the process: the shared machine's wall time says little)
and its peak RSS (`ru_maxrss`, the whole process: body model, robot and the step). The retarget
case retargets the input motion (the collide step's output differs only on masked joints near
contacts; its cost per frame is the same kind). `collide_nocollision_s` is the collide step's CPU
time on a clip with no collision (a 120 fps, 600-frame idle pose, arms away from the body).

    python benchmarks/long_sequence.py                   # 150 and 2400 frames
    python benchmarks/long_sequence.py --frames 150 20000

`*_linear_ratio` = (CPU s per frame at the longest length) / (CPU s per frame at the shortest):
1.0 is linear; the target is ≤ 2.

Measured 2026-11-29 on the shared 2-core machine (load 5-20; CPU time, not wall):
    150 frames:    collide 3.15 CPU-s (21.0 ms/frame, 593 MB), retarget 5.83 CPU-s (38.9 ms/frame,
                   904 MB; 7.1-16 CPU-s in other runs: torch's threads spin under load)
    2,400 frames:  collide 47.0 CPU-s (19.6 ms/frame, 657 MB), retarget 99.6 CPU-s (41.5 ms/frame,
                   1,050 MB)
    20,000 frames: collide 379 CPU-s (19.0 ms/frame, 1,126 MB), retarget 914 CPU-s (45.7 ms/frame,
                   1,459 MB)
    RESULT frames=150,2400 collide_linear_ratio=0.93 collide_rss_mb=657 retarget_linear_ratio=1.07
    retarget_rss_mb=1050 collide_nocollision_s=1.43
The no-collision clip runs 0 optimiser steps; its 1.4-1.8 CPU-s are mostly the mesh judge's depth
of every frame (its metrics). A fresh checkout's first run adds ~25 CPU-s of numba compilation
(26.4 CPU-s for the same clip), which later runs load from the cache.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def long_motion(frames: int, seed: int = 0):
    """`frames` frames of synthetic clips `generate_sequence(seed, 0), (seed, 1), ...` end to end."""
    import numpy as np

    from embody.motion import Motion
    from embody.synth import generate_sequence
    poses, transl, betas, n, i = [], [], None, 0, 0
    while n < frames:
        clip = generate_sequence(seed, i)
        poses.append(np.asarray(clip.pose))
        transl.append(np.asarray(clip.transl) if clip.transl is not None
                      else np.zeros((clip.num_frames, 3)))
        betas = clip.betas if betas is None else betas
        n += clip.num_frames
        i += 1
    return Motion(pose=np.concatenate(poses)[:frames], transl=np.concatenate(transl)[:frames],
                  betas=np.asarray(betas), fps=30.0)


def child(step: str, frames: int) -> dict:
    """One case in this process: CPU seconds of the step and the process's peak RSS (MB)."""
    from embody.body import load_body_model
    from embody.collision.windows import mitigate_windowed
    from embody.config import load_config
    from embody.synth.idle import idle_motion

    cfg = load_config(sets=[f"io.max_frames={max(frames, 2)}"])
    body = load_body_model(cfg.body)
    motion = idle_motion() if step == "nocollision" else long_motion(frames)
    extra: dict = {}
    if step in ("collide", "nocollision"):
        c0, w0 = time.process_time(), time.perf_counter()
        res = mitigate_windowed(motion, body, cfg.collision)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        extra = {"steps": int(res.metrics.get("steps", 0)),
                 "polish_steps": int(res.metrics.get("polish_steps", 0)),
                 "windows": int(res.metrics.get("windows", 1)),
                 "max_depth_mm_after": round(float(res.metrics.get("max_depth_mm_after", 0)), 2),
                 "energy_before": float(res.frame_energy_before.mean()),
                 "energy_after": float(res.frame_energy_after.mean())}
    else:
        from embody.retarget import build_targets, shape_fit
        from embody.retarget.windows import solve_windowed
        from embody.robot import load_robot
        robot = load_robot(cfg.robot)
        fit = shape_fit(robot, body, cfg.ik)
        c0, w0 = time.process_time(), time.perf_counter()
        sol = solve_windowed(robot, build_targets(motion, body, fit, robot, cfg.ik), cfg.ik)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        extra = {"q_shape": list(sol.q.shape)}
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"step": step, "frames": motion.num_frames, "cpu_s": round(cpu, 2),
            "wall_s": round(wall, 2), "cpu_ms_per_frame": round(1000 * cpu / motion.num_frames, 3),
            "peak_rss_mb": round(rss), **extra}


def _run(step: str, frames: int) -> dict | None:
    out = subprocess.run([sys.executable, __file__, "--child", step, str(frames)],
                         stdout=subprocess.PIPE, text=True, cwd=ROOT)
    if out.returncode != 0:
        return None
    row = json.loads(out.stdout.strip().splitlines()[-1])
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[150, 2400])
    ap.add_argument("--steps", nargs="+", default=["collide", "retarget"],
                    choices=["collide", "retarget"])
    ap.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child[0], int(args.child[1]))))
        return
    short, long = min(args.frames), max(args.frames)
    result: dict[str, str] = {}
    for step in args.steps:
        rows = {f: _run(step, f) for f in sorted(set(args.frames))}
        if rows[short] and rows[long]:
            ratio = rows[long]["cpu_ms_per_frame"] / max(rows[short]["cpu_ms_per_frame"], 1e-9)
            result[f"{step}_linear_ratio"] = f"{ratio:.2f}"
            result[f"{step}_rss_mb"] = str(rows[long]["peak_rss_mb"])
        else:
            result[f"{step}_linear_ratio"] = result[f"{step}_rss_mb"] = "failed"
    if "collide" in args.steps:
        row = _run("nocollision", 600)
        result["collide_nocollision_s"] = f"{row['cpu_s']:.2f}" if row else "failed"
    print(f"RESULT frames={short},{long} " + " ".join(f"{k}={v}" for k, v in result.items()))


if __name__ == "__main__":
    main()
