"""Profile of the default pipeline's per-sequence steps, in one process, with cProfile.

The flow runs steps in Prefect worker threads, which cProfile does not follow; this script calls
the same library functions the steps call (`tasks/stages.py`), in the same order, on the first N
sequences of the default synthetic set, with the default config, and prints
  * wall seconds per step and sequence (collide, retarget, refine, render, metrics), and
  * inside those, the cumulative seconds of the kernels that matter: FK, IK Jacobians, the
    self-collision proxies, the banded solve, MuJoCo verification/validation, offscreen rendering.

    python benchmarks/profile_pipeline.py [--n 3] [--top 25] [--pstats out.pstats]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import tempfile
import time
from collections import defaultdict
from pathlib import Path

#: (label, file suffix, function name) of the kernels reported from the profile.
KERNELS = [
    ("fk.forward", "embody/robot/fk.py", "forward"),
    ("ik.residuals", "embody/retarget/costs.py", "lazy"),
    ("ik.jacobian", "embody/retarget/costs.py", "_jacobian"),
    ("ik.collision_proxies", "embody/retarget/costs.py", "_collision"),
    ("ik.banded_solve", "embody/retarget/banded.py", "block_pentadiagonal_solve"),
    ("ik.solve", "embody/retarget/ik.py", "solve"),
    ("mujoco.verify", "embody/retarget/verify.py", "verify"),
    ("mujoco.validation_counts", "embody/retarget/validation.py", "validation_counts"),
    ("collision.frame_energies", "embody/collision/energy.py", "frame_energies"),
    ("collision.skinning", "embody/collision/energy.py", "skinned_points"),
    ("render.sequence", "embody/render/record.py", "render_sequence"),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=3)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--pstats", type=Path, default=None)
    args = parser.parse_args()

    import numpy as np
    import torch
    torch.set_num_threads(1)
    from embody.body import load_body_model
    from embody.collision import mitigate
    from embody.config import Config
    from embody.critic.refine import make_critic, refine
    from embody.io import load_dataset
    from embody.metrics import mean_jerk
    from embody.render import select_keyframes  # noqa: F401  (the render step's import)
    from embody.render.record import render_sequence
    from embody.retarget import build_targets, shape_fit, solve
    from embody.retarget.validation import validation_counts
    from embody.robot import load_robot
    from embody.synth import default_dataset

    cfg = Config()
    data = default_dataset(Path(tempfile.mkdtemp(prefix="embody-prof-")))
    refs = list(load_dataset(data))[: args.n]
    body, robot = load_body_model(cfg.body), load_robot(cfg.robot)
    critic = make_critic(cfg.critic)
    t0 = time.perf_counter()
    fit = shape_fit(robot, body, cfg.ik)
    print(f"shape_fit (once per run) {time.perf_counter() - t0:.2f} s")

    wall: dict[str, float] = defaultdict(float)
    prof = cProfile.Profile()
    prof.enable()
    for ref in refs:
        t = time.perf_counter()
        motion = mitigate(ref.load(), body, cfg.collision).motion
        wall["collide"] += time.perf_counter() - t
        t = time.perf_counter()
        targets = build_targets(motion, body, fit, robot)
        ik = solve(robot, targets, cfg.ik)
        wall["retarget"] += time.perf_counter() - t
        t = time.perf_counter()
        result = refine(motion, body, fit, robot, targets, ik, cfg.critic, cfg.ik, cfg.render,
                        critic=critic)
        wall["refine"] += time.perf_counter() - t
        t = time.perf_counter()
        render_sequence(motion, body, fit, robot, result.q, result.keyframes, cfg.render, ref.id)
        wall["render"] += time.perf_counter() - t
        t = time.perf_counter()
        q = np.asarray(result.q)
        mean_jerk(q, ik.fps)
        validation_counts(robot, q, ik.fps)
        wall["metrics"] += time.perf_counter() - t
    prof.disable()

    n = len(refs)
    print(f"\nwall seconds per sequence (n={n}, 1 thread):")
    for step, secs in wall.items():
        print(f"  {step:10s} {secs / n:7.2f}")
    stats = pstats.Stats(prof)
    if args.pstats:
        stats.dump_stats(args.pstats)
    cum: dict[str, float] = {}
    calls: dict[str, int] = {}
    for (file, _, func), (_, ncalls, _, ct, _) in stats.stats.items():  # type: ignore[attr-defined]
        for label, suffix, name in KERNELS:
            if file.endswith(suffix) and func == name:
                cum[label] = cum.get(label, 0.0) + ct
                calls[label] = calls.get(label, 0) + ncalls
    print("\nkernels (cumulative seconds per sequence, calls per sequence):")
    for label, _, _ in KERNELS:
        if label in cum:
            print(f"  {label:26s} {cum[label] / n:7.2f} s  {calls[label] / n:8.0f} calls")
    print(f"\ntop {args.top} functions by cumulative time:")
    stats.sort_stats("cumulative").print_stats(args.top)
    total = sum(wall.values()) / n
    print("RESULT " + " ".join([f"seconds_per_seq_1thread={total:.2f}"]
                               + [f"{k}_s={v / n:.2f}" for k, v in wall.items()]
                               + [f"{k}_s={v / n:.2f}" for k, v in cum.items()]))


if __name__ == "__main__":
    main()
