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

import hashlib
import time

import numpy as np
import torch

from _collide_cpu import prepare, time_judge
from embody.collision import mitigate
from embody.io import load


def main() -> None:
    torch.set_num_threads(1)
    paths, body, cfg = prepare(mitigate, __doc__.splitlines()[0])
    judge_cpu = time_judge("_depths")
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
