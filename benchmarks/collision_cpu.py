"""`mitigate` over the default dataset in one process: CPU seconds per 150 frames without the
before/after mesh judge (`optimize._depths`, timed in CPU and taken out, as `depth_s` is taken
out of the wall figure), and a hash of the output poses.

Why: on a loaded machine the wall figure of `benchmarks/collision.py` swings 2-5x, while this
process's CPU time does not (much). To compare two checkouts, run it with each on PYTHONPATH
back to back (alternating, twice): equal hashes mean the same poses bit for bit. One untimed
`mitigate` on the first sequence loads the compiled kernels first (numba's cache: a per-process
cost, not a per-150-frame one); the judge's memo is cleared after it. Ends with one `RESULT`
line.

    PYTHONPATH=<checkout> python benchmarks/collision_cpu.py [--data DIR] [--n 24]
"""

from __future__ import annotations

import argparse
import hashlib
import time
from pathlib import Path

import numpy as np
import torch

from embody.body import MannequinBody
from embody.collision import depth, mitigate, optimize, part_volumes
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--n", type=int, default=24)
    args = ap.parse_args()
    torch.set_num_threads(1)
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))[: args.n]
    body, cfg = MannequinBody(), CollisionConfig()
    part_volumes(body)
    mitigate(load(paths[0]), body, cfg)  # warm-up: compiled kernels loaded, untimed
    depth._memo.clear()
    judge_cpu = [0.0]
    depths = optimize._depths

    def timed_depths(*a, **k):
        c = time.process_time()
        out = depths(*a, **k)
        judge_cpu[0] += time.process_time() - c
        return out

    optimize._depths = timed_depths
    cpu, wall, steps = [], [], 0
    digest = hashlib.sha256()
    for p in paths:
        motion = load(p)
        judge_cpu[0] = 0.0
        c = time.process_time()
        r = mitigate(motion, body, cfg)
        c = time.process_time() - c
        frames = r.metrics["frames"]
        cpu.append((c - judge_cpu[0]) / frames * 150)
        wall.append(r.metrics["runtime_s"] / frames * 150)
        steps += r.metrics["steps"]
        digest.update(np.ascontiguousarray(r.motion.pose).tobytes())
    print(f"RESULT sequences={len(paths)} cpu_seconds_per_150_frames_no_judge={np.mean(cpu):.3f} "
          f"seconds_per_150_frames_1thread={np.mean(wall):.3f} steps={steps} "
          f"pose_sha256={digest.hexdigest()[:16]}")


if __name__ == "__main__":
    main()
