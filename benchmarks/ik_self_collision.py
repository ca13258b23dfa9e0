"""MuJoCo self-collision frames of the IK output on the default synthetic run.

Input is what the pipeline feeds the IK: `embody synth --n 24 --seed 0`, then stage 1 collision
mitigation (default config). The mitigated motions are cached under `--cache` (its time is not
counted). Per sequence: self-collision frames (penetrating contacts between non-adjacent bodies,
`embody.robot.contacts`), the colliding body pairs, mean wrist error and solve time.

Measured (2 shared cores): before, margin 8 mm and a tracking phase without the collision term,
`RESULT self_collision_frames=136 wrist_mm_mean=4.72 seconds_total=8.8`; with the defaults now
(margin 15 mm, tracking_collision 1e-3) `self_collision_frames=9 wrist_mm_mean=5.61 seconds_total=11.3`.

Usage: python benchmarks/ik_self_collision.py [--work /tmp/sc] [--sequences 24]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from embody import io  # noqa: E402
from embody.body import load_body_model  # noqa: E402
from embody.collision import mitigate  # noqa: E402
from embody.config import Config  # noqa: E402
from embody.retarget import build_targets, shape_fit, solve  # noqa: E402
from embody.robot import load_robot  # noqa: E402
from embody.robot.contacts import contact_pairs  # noqa: E402
from embody.synth import generate_dataset  # noqa: E402


def mitigated(work: Path, n: int, body, config: Config) -> list[Path]:
    """Paths of the mitigated motions, computed once."""
    raw, out = work / "data", work / "mitigated"
    if not raw.exists():
        generate_dataset(raw, n, 0)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for src in sorted(raw.glob("seq_*.npz"))[:n]:
        dst = out / src.name
        if not dst.exists():
            io.save(mitigate(io.load(src), body, config.collision).motion, dst)
        paths.append(dst)
    return paths


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, default=Path("/tmp/sc"))
    ap.add_argument("--sequences", type=int, default=24)
    args = ap.parse_args()
    torch.set_num_threads(1)
    config = Config()
    robot, body = load_robot(config.robot), load_body_model(config.body)
    fit = shape_fit(robot, body, config.ik)
    frames_total, wrist, seconds = 0, [], 0.0
    for path in mitigated(args.work, args.sequences, body, config):
        targets = build_targets(io.load(path), body, fit, robot)
        t0 = time.perf_counter()
        sol = solve(robot, targets, config.ik)
        dt = time.perf_counter() - t0
        n = int(sol.metrics["self_collision_frames"])
        pairs = contact_pairs(robot, sol.q) if n else {}
        frames_total += n
        seconds += dt
        wrist.append(sol.metrics["wrist_pos_err_mm"])
        print(f"{path.stem} frames={len(sol.q)} self_collision_frames={n} "
              f"wrist_mm={wrist[-1]:.2f} seconds={dt:.2f} pairs={dict(pairs)}", flush=True)
    print(f"RESULT self_collision_frames={frames_total} wrist_mm_mean={np.mean(wrist):.2f} "
          f"seconds_total={seconds:.1f}")


if __name__ == "__main__":
    main()
