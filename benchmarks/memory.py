"""Peak memory of one long sequence through load → collide → retarget → metrics.

Each case runs in a fresh subprocess and reports its peak RSS (`ru_maxrss`), so cases do not
share allocator state. The motion is a 30 fps arm swing through the chest (it collides in every
frame), saved as an AMASS-style npz and loaded back with `io.max_frames` raised to fit.
Peak RSS per optimiser step does not grow with the step count, so the collision and IK
iteration counts are cut (`--collision-steps`, `--ik-iterations`) to keep the run short; the
peaks are those of the default settings otherwise. `--unwindowed` sets the collision window
past the sequence length: the memory before windowing (issue 10 measured >20 GB at 20,000).

    python benchmarks/memory.py [--frames 2000 20000] [--unwindowed] [--fast] [--collision-steps 3]

Measured 2026-11-23 on the shared 2-core machine (load ~7), `--fast --collision-steps 1
--ik-iterations 1`, when this script still called the unwindowed `solve`:
    RESULT mode=windowed-fast peak_rss_mb_2000=3009 peak_rss_mb_20000=16766
(collide bounded: 1,154 MB at 2,000 frames, 1,242 MB at 20,000; the 16.8 GB was the IK solving
all 20,000 frames at once). Since `embody.retarget.solve` is the windowed solver, `--fast`
(default steps, depth check off) gave 2,000 frames: collide 1,810 MB, retarget 2,665 MB;
20,000 frames: collide 1,921 MB (893 s on the loaded machine); the 20,000-frame IK alone
(11 windows, 2 iterations, NumPy FK, contact repair and control-rate trajectory included)
held 1.43 GB between windows, peak 3,197 MB, in 56 s. Issue 10 measured >20 GB (collide) and
>12 GB (no collide) at 20,000 frames before windowing.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _motion(frames: int):
    import numpy as np

    from embody.motion import JOINT_NAMES, Motion
    j = JOINT_NAMES.index
    s = 0.5 - 0.5 * np.cos(np.linspace(0, 2 * np.pi * frames / 60, frames))
    pose = np.zeros((frames, 55, 3))
    pose[:, j("left_shoulder")] = [0.0, -1.0, -0.3]
    pose[:, j("right_shoulder")] = [0.0, 1.0, 0.3]
    pose[:, j("left_elbow"), 1] = -1.6 - 0.8 * s
    pose[:, j("right_elbow"), 1] = 1.6 + 0.8 * s
    pose[:, 25:40, 2] = -0.8 * s[:, None]
    pose[:, 40:55, 2] = 0.8 * s[:, None]
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=30.0)


def child(frames: int, unwindowed: bool, collision_steps: int, ik_iterations: int,
          fast: bool) -> dict:
    """One case in this process: stage timings and the process's peak RSS (MB)."""
    from embody.body import load_body_model
    from embody.collision.windows import mitigate_windowed
    from embody.config import load_config
    from embody.io import load, save
    from embody.metrics import mean_jerk
    from embody.retarget import build_targets, shape_fit, solve
    from embody.retarget.validation import validation_counts
    from embody.robot import load_robot

    # The mesh penetration-depth check is an evaluation, not part of the memory question, and
    # costs ~0.1-0.3 s a frame: off here.
    sets = [f"io.max_frames={max(frames, 2)}", f"collision.steps={collision_steps}",
            "collision.depth_metrics=false",
            f"ik.iterations={ik_iterations}", f"ik.tracking_iterations={min(ik_iterations, 8)}"]
    if unwindowed:
        sets += [f"collision.window_frames={frames + 1}", f"ik.window_frames={frames + 1}"]
    if fast:  # fewer collision points and the NumPy FK: same memory shape, a fraction of the time
        sets += ["collision.vertex_stride=64", "ik.kinematics=tree"]
    cfg = load_config(sets=sets)
    times, rss = {}, {}

    def mark(name: str, t0: float) -> None:
        times[name] = round(time.perf_counter() - t0, 1)
        rss[name] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        print(f"  {frames} frames: {name} done in {times[name]} s, peak RSS {rss[name]} MB",
              file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        path = save(_motion(frames), Path(tmp) / "long.npz")
        motion = load(path, limits=cfg.io)
    mark("load", t0)
    body = load_body_model(cfg.body)
    t0 = time.perf_counter()
    fixed = mitigate_windowed(motion, body, cfg.collision)
    mark("collide", t0)
    robot = load_robot(cfg.robot)
    fit = shape_fit(robot, body, cfg.ik)
    t0 = time.perf_counter()
    sol = solve(robot, build_targets(fixed.motion, body, fit, robot), cfg.ik)
    mark("retarget", t0)
    t0 = time.perf_counter()
    q = sol.q
    validation_counts(robot, q, sol.fps)
    mean_jerk(q, sol.fps)
    mark("metrics", t0)
    return {"frames": frames, "windows": fixed.metrics.get("windows", 1), "times_s": times,
            "peak_rss_mb_after": rss}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[2000, 20000])
    ap.add_argument("--unwindowed", action="store_true")
    ap.add_argument("--collision-steps", type=int, default=3)
    ap.add_argument("--ik-iterations", type=int, default=2)
    ap.add_argument("--fast", action="store_true",
                    help="collision.vertex_stride=64 and ik.kinematics=tree (for a busy machine)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child, args.unwindowed, args.collision_steps,
                               args.ik_iterations, args.fast)))
        return
    results = {}
    for frames in args.frames:
        cmd = [sys.executable, __file__, "--child", str(frames), "--collision-steps",
               str(args.collision_steps), "--ik-iterations", str(args.ik_iterations)]
        cmd += ["--unwindowed"] if args.unwindowed else []
        cmd += ["--fast"] if args.fast else []
        out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, cwd=ROOT)
        if out.returncode != 0:
            results[frames] = None
            continue
        row = json.loads(out.stdout.strip().splitlines()[-1])
        print(json.dumps(row))
        results[frames] = max(row["peak_rss_mb_after"].values())
    mode = ("unwindowed" if args.unwindowed else "windowed") + ("-fast" if args.fast else "")
    print("RESULT " + f"mode={mode} " + " ".join(
        f"peak_rss_mb_{f}={v if v is not None else 'failed'}" for f, v in results.items()))


if __name__ == "__main__":
    main()
