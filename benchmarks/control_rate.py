"""Cost and effect of making the trajectories collision-free by construction (`ik.contact_repair`).

Per synthetic sequence (after stage-1 collision mitigation, as `ik_self_collision.py`), the IK is
solved twice with the default config: with the MuJoCo contact repair off (the proxies alone; the
control-rate array is then the plain resample) and on (`retarget.control`: repair at the source
rate and at every 50 Hz control sample). Reported: MuJoCo self-collision frames at both rates,
solve seconds, the repair's own seconds (`separate` + `control_trajectory` timed alone on the
repair-off solution, less noisy than the difference of two solves on a shared machine), the wrist
error and the mean jerk of the control-rate trajectory, on and off.

Usage: python benchmarks/control_rate.py [--sequences 8] [--work /tmp/sc]

Measured 2026-11-23 (2 shared CPU cores, default config, 8 sequences): off 5 source-rate and 19
control-rate collision frames, on 0 and 0; the repair alone 5.1 s = 10.5 % of the solve time
(48.6 s); wrist error 8.46 → 8.82 mm (seq_006, the one with deep hand overlaps, 44.0 → 46.9 mm);
control-rate jerk 1901 → 1972.
`RESULT sequences=8 collision_frames_off_src=5 collision_frames_off_control=19
collision_frames_on_src=0 collision_frames_on_control=0 seconds_off=48.6 seconds_on=44.2
repair_s=5.10 repair_pct_of_solve=10.5 wrist_mm_off=8.46 wrist_mm_on=8.82 jerk_off=1901.4
jerk_on=1971.8`
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ik_self_collision import mitigated  # noqa: E402

from embody import io  # noqa: E402
from embody.body import load_body_model  # noqa: E402
from embody.config import Config  # noqa: E402
from embody.metrics import mean_jerk  # noqa: E402
from embody.retarget import build_targets, shape_fit, solve  # noqa: E402
from embody.retarget.control import control_trajectory, separate  # noqa: E402
from embody.retarget.validation import validation_counts  # noqa: E402
from embody.robot import load_robot  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, default=Path("/tmp/sc"))
    ap.add_argument("--sequences", type=int, default=8)
    args = ap.parse_args()
    torch.set_num_threads(1)
    config = Config()
    robot, body = load_robot(config.robot), load_body_model(config.body)
    fit = shape_fit(robot, body, config.ik)
    cfg_on, cfg_off = config.ik, config.ik.model_copy(update={"contact_repair": False})
    tot = {"off": [0, 0, 0.0], "on": [0, 0, 0.0]}
    wrist = {"off": [], "on": []}
    jerk = {"off": [], "on": []}
    rate = config.ik.control_rate_hz
    repair_s = 0.0
    for path in mitigated(args.work, args.sequences, body, config):
        targets = build_targets(io.load(path), body, fit, robot)
        line = [path.stem]
        for name, cfg in (("off", cfg_off), ("on", cfg_on)):
            t0 = time.perf_counter()
            sol = solve(robot, targets, cfg)
            dt = time.perf_counter() - t0
            src = int(validation_counts(robot, sol.q, sol.fps)["self_collision_frames"])
            ctl = validation_counts(robot, sol.q_control, rate)
            tot[name][0] += src
            tot[name][1] += int(ctl["self_collision_frames"])
            tot[name][2] += dt
            wrist[name].append(sol.metrics["wrist_pos_err_mm"])
            jerk[name].append(mean_jerk(sol.q_control[:, robot.ik_mask], rate))
            if name == "off":
                t1 = time.perf_counter()
                control_trajectory(robot, separate(robot, sol.q, sol.fps), sol.fps, rate)
                repair_s += time.perf_counter() - t1
            line.append(f"{name}: src={src} ctl={int(ctl['self_collision_frames'])} "
                        f"vel={int(ctl['velocity_violations'])} s={dt:.2f} "
                        f"wrist={wrist[name][-1]:.2f}")
        print("  ".join(line), flush=True)
    off, on = tot["off"], tot["on"]
    print(f"RESULT sequences={len(wrist['on'])} collision_frames_off_src={off[0]} "
          f"collision_frames_off_control={off[1]} collision_frames_on_src={on[0]} "
          f"collision_frames_on_control={on[1]} seconds_off={off[2]:.1f} seconds_on={on[2]:.1f} "
          f"repair_s={repair_s:.2f} repair_pct_of_solve={100 * repair_s / max(off[2], 1e-9):.1f} "
          f"wrist_mm_off={np.mean(wrist['off']):.2f} wrist_mm_on={np.mean(wrist['on']):.2f} "
          f"jerk_off={np.mean(jerk['off']):.1f} jerk_on={np.mean(jerk['on']):.1f}")


if __name__ == "__main__":
    main()
