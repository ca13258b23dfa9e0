"""The pull-back's search alone, A/B: a reference `pull_back` (another copy of
`embody/collision/optimize.py`, e.g. `git show <rev>:embody/collision/optimize.py`) against
the current one, on the same optimised + polished poses (`mitigate` with `pull_back` off).

CPU seconds (`time.process_time`, one thread) of each call, back to back in one process; Pose
MSE and the judge's max depth of each result. Ends with one `RESULT` line.

    python benchmarks/collision_pull_back.py --ref /tmp/old_optimize.py [--seqs 0 3 12 14 15]
        [--set solver=gauss_newton ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from embody.body import MannequinBody
from embody.collision import mitigate
from embody.collision import optimize
from embody.collision.metrics import pose_mse
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset
from _reference import load_reference  # benchmarks/, the script's own folder

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--ref", required=True, help="path of the reference optimize.py")
    ap.add_argument("--seqs", type=int, nargs="+", default=[0, 3, 12, 14, 15])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    torch.set_num_threads(1)
    ref = load_reference(args.ref, "ref_optimize")
    over = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    cfg = CollisionConfig.model_validate({**CollisionConfig().model_dump(), **over})
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))
    body = MannequinBody()
    cpu = {"ref": 0.0, "new": 0.0}
    mse = {"ref": [], "new": []}
    worst = {"ref": 0.0, "new": 0.0}
    frames = 0
    for i in args.seqs:
        motion = load(paths[i])
        polished = mitigate(motion, body, cfg.model_copy(update={"pull_back": False})).motion
        d0, d1 = optimize._depths(body, motion, polished.pose, cfg)
        frames += len(motion.pose)
        row = []
        for name, fn in (("ref", lambda: ref.pull_back(body, motion, polished.pose, d1, cfg)),
                         ("new", lambda: optimize.pull_back(body, motion, polished.pose, d1,
                                                            cfg, d0))):
            t = time.process_time()
            pose, d = fn()
            cpu[name] += time.process_time() - t
            mse[name].append(pose_mse(pose, motion.pose))
            worst[name] = max(worst[name], float(d.max()))
            row.append(f"{name} mse={mse[name][-1]:.5f} max_mm={1e3 * d.max():.2f}")
        print(f"seq {i:3d} T={len(motion.pose)} polished mse={pose_mse(polished.pose, motion.pose):.5f} "
              + " ".join(row), flush=True)
    per150 = {k: v / frames * 150 for k, v in cpu.items()}
    print("RESULT " + " ".join(
        f"{k}_pull_back_cpu_per_150_frames={per150[k]:.2f} {k}_pose_mse_median="
        f"{np.median(mse[k]):.5f} {k}_max_depth_mm={1e3 * worst[k]:.2f}" for k in ("ref", "new"))
        + f" max_abs_mse_diff={np.max(np.abs(np.subtract(mse['new'], mse['ref']))):.2e}"
        + f" frames={frames}")


if __name__ == "__main__":
    main()
