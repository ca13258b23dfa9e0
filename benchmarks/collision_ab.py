"""The whole collide step (`mitigate`: optimiser, polish, judge, pull-back), A/B: a reference
copy of `embody/collision/optimize.py` (e.g. `git show <rev>:embody/collision/optimize.py`),
optionally with a reference `energy.py` too (`--ref-energy`: the reference optimiser then runs
on it, the current one on the current energy), with its config against the current one with its config, back to back in one process on the
same sequences, so the CPU figures share the machine's load. The mesh judge's memo is cleared before each
side, so neither reuses the other's judged frames.

CPU seconds (`time.process_time`, one torch thread) per 150 frames of each, with steps, Pose
MSE and the judge's max depth per sequence. Ends with one `RESULT` line.

    python benchmarks/collision_ab.py --ref /tmp/old_optimize.py [--ref-energy /tmp/old_energy.py]
        [--seqs 1 2 3 14] [--warmup 17]
        [--ref-set early_stop_stall=20] [--set early_stop_stall=1]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import yaml

from embody.body import MannequinBody
from embody.collision import depth, optimize, part_volumes
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset
from _reference import load_reference  # benchmarks/, the script's own folder

ROOT = Path(__file__).resolve().parents[1]


def _cfg(pairs: list[str]) -> CollisionConfig:
    return CollisionConfig(**{k: yaml.safe_load(v) for k, v in (p.split("=", 1) for p in pairs)})


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--ref", required=True, help="path of the reference optimize.py")
    ap.add_argument("--seqs", type=int, nargs="+", default=[1, 2, 3, 14])
    ap.add_argument("--ref-energy", help="path of the reference energy.py (default: current)")
    ap.add_argument("--ref-set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--warmup", type=int, metavar="SEQ",
                    help="run both sides once on this sequence first, untimed (the first call "
                         "in a process pays the judge's compiled kernels and the model caches)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    current = sys.modules["embody.collision.energy"]
    if args.ref_energy:  # the reference optimize.py imports the reference energy.py
        sys.modules["embody.collision.energy"] = load_reference(args.ref_energy, "energy_ref")
    try:
        ref = load_reference(args.ref, "optimize_ref")
    finally:
        sys.modules["embody.collision.energy"] = current
    body = MannequinBody()
    part_volumes(body)
    base, cand = _cfg(args.ref_set), _cfg(args.set)
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))
    if args.warmup is not None:
        m = load(paths[args.warmup])
        ref.mitigate(m, body, base)
        optimize.mitigate(m, body, cand)
    cpu_ref = cpu_new = 0.0
    frames = 0
    for i in args.seqs:
        m = load(paths[i])
        depth._memo.clear()  # each side pays its own judge calls (the memo would carry over)
        t0 = time.process_time()
        ra = ref.mitigate(m, body, base)
        t1 = time.process_time()
        depth._memo.clear()
        rb = optimize.mitigate(m, body, cand)
        t2 = time.process_time()
        a, b = ra.metrics, rb.metrics
        cpu_ref, cpu_new, frames = cpu_ref + t1 - t0, cpu_new + t2 - t1, frames + len(m.pose)
        same = bool((ra.motion.pose == rb.motion.pose).all())
        print(f"seq_{i:03d} ref {t1 - t0:.2f}s steps={a['steps']} mse={a['pose_mse']:.5f} "
              f"max_mm={a['max_depth_mm_after']:.2f} | new {t2 - t1:.2f}s steps={b['steps']} "
              f"mse={b['pose_mse']:.5f} max_mm={b['max_depth_mm_after']:.2f} same_pose={same}", flush=True)
    print(f"RESULT ref_cpu_per_150_frames={cpu_ref / frames * 150:.2f} "
          f"new_cpu_per_150_frames={cpu_new / frames * 150:.2f} frames={frames}")


if __name__ == "__main__":
    main()
