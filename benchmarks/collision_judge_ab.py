"""The collide step's judge work alone, A/B: `optimize.judge` (the mesh judge's depths before and
after, the depth-guided polish, the pull-back) of a reference copy of
`embody/collision/optimize.py` and `frame_kernels.py` (e.g. `git show <rev>:<path>`) against the
current ones, on the same inputs: each sequence's optimised pose as `mitigate` hands it to
`judge` (captured once, current code).

CPU seconds (`time.process_time`, one thread) of each `judge` call, the two alternating (order
swapped every sequence), the judge's memo cleared before each; frames the judge skinned and
tested (memo misses); Pose MSE / ΔAccel medians and the max depth after of each result. The
reference runs with `--ref-set` overrides (e.g. the old `pull_back_window_s`). Ends with one
`RESULT` line.

    python benchmarks/collision_judge_ab.py --ref /tmp/old_optimize.py \
        --ref-kernels /tmp/old_frame_kernels.py [--n 24] [--ref-set pull_back_window_s=0.25]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from embody.body import MannequinBody
from embody.collision import depth, frame_kernels, optimize
from embody.collision.metrics import accel_mse, pose_mse
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset
from _reference import load_reference  # benchmarks/, the script's own folder

ROOT = Path(__file__).resolve().parents[1]


def _captured(motion, body, cfg: CollisionConfig):
    """(pose, energies after, mask) that `mitigate` hands to `judge`."""
    seen = {}
    real = optimize.judge

    def spy(body, motion, fixed, after, idx, cfg, enabled):
        seen.update(pose=fixed.pose.copy(), after=after.copy(), idx=idx.copy())
        return real(body, motion, fixed, after, idx, cfg, enabled)

    optimize.judge = spy
    try:
        optimize.mitigate(motion, body, cfg)
    finally:
        optimize.judge = real
    return seen["pose"], seen["after"], seen["idx"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--ref", required=True, help="path of the reference optimize.py")
    ap.add_argument("--ref-kernels", required=True, help="path of the reference frame_kernels.py")
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--ref-set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    torch.set_num_threads(1)
    ref = load_reference(args.ref, "ref_optimize")
    ref_kernels = load_reference(args.ref_kernels, "ref_frame_kernels")
    cfg = CollisionConfig()
    over = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.ref_set)}
    ref_cfg = CollisionConfig.model_validate({**cfg.model_dump(), **over})
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))[: args.n]
    body = MannequinBody()
    judged = {"ref": 0, "new": 0}
    real_depths = depth.frame_depths

    def counting(name):
        def frame_depths(mesh, vertices):
            judged[name] += len(vertices)
            return real_depths(mesh, vertices)
        return frame_depths

    def run(name, motion, pose, after, idx):
        mod, kernels, c = (ref, ref_kernels, ref_cfg) if name == "ref" else (optimize,
                                                                            frame_kernels, cfg)
        depth._memo.clear()
        depth.frame_kernels, depth.frame_depths = kernels, counting(name)
        try:
            t = time.process_time()
            fixed, _, metrics, _ = mod.judge(body, motion, motion.with_pose(pose), after, idx, c,
                                             True)
            return time.process_time() - t, fixed.pose, metrics
        finally:
            depth.frame_kernels, depth.frame_depths = frame_kernels, real_depths

    m0 = load(paths[0])  # warm both kernel sets (numba caches) and the mesh
    for kernels in (ref_kernels, frame_kernels):
        depth._memo.clear()
        depth.frame_kernels = kernels
        depth.motion_depths(body, m0.pose[:8], m0.betas, cfg.allow_pairs)
    depth.frame_kernels = frame_kernels
    cpu = {"ref": 0.0, "new": 0.0}
    mse, dacc, worst = {"ref": [], "new": []}, {"ref": [], "new": []}, {"ref": 0.0, "new": 0.0}
    frames = 0
    for k, p in enumerate(paths):
        motion = load(p)
        pose, after, idx = _captured(motion, body, cfg)
        frames += len(pose)
        row = {}
        for name in (("ref", "new") if k % 2 == 0 else ("new", "ref")):
            s, out, metrics = run(name, motion, pose, after, idx)
            cpu[name] += s
            mse[name].append(pose_mse(out, motion.pose))
            dacc[name].append(accel_mse(out) - accel_mse(motion.pose))
            worst[name] = max(worst[name], metrics["max_depth_mm_after"])
            row[name] = (s, mse[name][-1], metrics["max_depth_mm_after"],
                         metrics["max_depth_mm_before"])
        assert row["ref"][3] == row["new"][3], "the depths before differ"
        print(f"{p.stem} T={len(pose)} cpu ref {row['ref'][0]:.2f} new {row['new'][0]:.2f} "
              f"mse ref {row['ref'][1]:.6f} new {row['new'][1]:.6f} "
              f"depth_mm ref {row['ref'][2]:.3f} new {row['new'][2]:.3f}", flush=True)
    per = {k: v / frames * 150 for k, v in cpu.items()}
    print(f"RESULT ref_cpu_per_150={per['ref']:.3f} new_cpu_per_150={per['new']:.3f} "
          f"speedup={per['ref'] / per['new']:.3f} ref_judged_frames={judged['ref']} "
          f"new_judged_frames={judged['new']} "
          f"ref_pose_mse_median={np.median(mse['ref']):.6f} "
          f"new_pose_mse_median={np.median(mse['new']):.6f} "
          f"ref_daccel_median={np.median(dacc['ref']):.3e} "
          f"new_daccel_median={np.median(dacc['new']):.3e} "
          f"ref_max_depth_mm_after={worst['ref']:.3f} new_max_depth_mm_after={worst['new']:.3f} "
          f"frames={frames}")


if __name__ == "__main__":
    main()
