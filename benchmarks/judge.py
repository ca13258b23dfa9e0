"""The mesh judge (`embody.collision.depth.motion_depths`): CPU seconds per 150 frames, today's
module vs the reference (the module at commit `REFERENCE`, loaded from git) in one process.

Both judge the input poses of the first `--n` default synthetic sequences, one thread,
alternating reference/new per sequence (back to back, so machine load hits both alike); time is
`time.process_time`. `max_abs_diff_m` is the largest per-frame depth difference, and
`zero_flips` counts frames judged clear (exactly 0) by one and not by the other. `--calls PATH`
instead replays a pickle of recorded judge calls (pose, betas, allow_pairs, depths) from a
mitigation run (before/after/pull-back poses) and compares against the recorded depths;
`--record PATH` writes that pickle: it runs `mitigate` (default config) on the `--n` sequences and
keeps every call of the judge. Record with the old code (PYTHONPATH at an old checkout), replay
with the new:

    python benchmarks/judge.py [--n 6] [--data data] [--ref REV] [--calls calls.pkl | --record calls.pkl]

Ends with `RESULT judge_s_per_150=… reference_s_per_150=… speedup=… max_abs_diff_m=…`.
"""

from __future__ import annotations

import argparse
import pickle
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from embody.body import MannequinBody
from embody.collision import depth
from embody.io import load
from embody.synth import default_dataset
from _reference import load_reference  # benchmarks/, the script's own folder

#: main before s9-judge: the judge as it was.
REFERENCE = "2b1c68c"
ROOT = Path(__file__).resolve().parents[1]


def reference_module(rev: str = REFERENCE):
    """`embody/collision/depth.py` at `rev`, imported under another name."""
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:embody/collision/depth.py"],
                         check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "depth_reference.py"
    path.write_text(src)
    return load_reference(path, "depth_reference")


def record(body: MannequinBody, paths: list[Path], out: str) -> None:
    """Every judge call of the collide step on `paths`: (seq, pose, betas, pairs, depths)."""
    from embody.collision import mitigate, optimize, part_volumes
    from embody.config.collision import CollisionConfig

    calls: list[tuple] = []
    judge = optimize.motion_depths
    name = ""

    def recorded(body, pose, betas, allow_pairs=(), device="cpu"):
        d = judge(body, pose, betas, allow_pairs, device)
        calls.append((name, np.array(pose), np.array(betas),
                      tuple(tuple(p) for p in allow_pairs), d.copy()))
        return d

    optimize.motion_depths = recorded
    part_volumes(body)
    for p in paths:
        name = p.stem
        mitigate(load(p), body, CollisionConfig())
        print(f"{name} calls={len(calls)}", flush=True)
    with open(out, "wb") as f:
        pickle.dump(calls, f)
    print(f"recorded calls={len(calls)} frames={sum(len(c[1]) for c in calls)} -> {out}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=6)
    ap.add_argument("--data", default="data")
    ap.add_argument("--calls", default=None, help="recorded judge calls (pickle) to replay")
    ap.add_argument("--record", default=None, help="write the judge calls of `mitigate` here")
    ap.add_argument("--ref", default=REFERENCE, help="git revision of the reference depth.py")
    args = ap.parse_args()
    torch.set_num_threads(1)
    body = MannequinBody()
    if args.record:
        record(body, sorted(default_dataset(args.data).glob("seq_*.npz"))[:args.n], args.record)
        return
    if args.calls:
        calls = pickle.load(open(args.calls, "rb"))
        jobs = [(c[0], c[1], c[2], c[3], c[4]) for c in calls]
        ref = None
    else:
        ref = reference_module(args.ref)
        jobs = [(p.stem, (m := load(p)).pose, m.betas, (), None)
                for p in sorted(default_dataset(args.data).glob("seq_*.npz"))[:args.n]]
    depth.motion_depths(body, jobs[0][1][:2], jobs[0][2])  # warm caches (mesh, shape)
    if ref is not None:
        ref.motion_depths(body, jobs[0][1][:2], jobs[0][2])
    t_new = t_ref = 0.0
    frames = flips = 0
    diff = 0.0
    for name, pose, betas, allow, known in jobs:
        if ref is not None:
            t = time.process_time()
            known = ref.motion_depths(body, pose, betas, allow)
            t_ref += time.process_time() - t
        t = time.process_time()
        ours = depth.motion_depths(body, pose, betas, allow)
        t_new += time.process_time() - t
        frames += len(pose)
        d = float(np.abs(ours - known).max()) if len(pose) else 0.0
        f = int(((ours == 0) != (known == 0)).sum())
        diff, flips = max(diff, d), flips + f
        if ref is not None or d > 0 or f:
            print(f"{name} frames={len(pose)} max_abs_diff_m={d:.3g} zero_flips={f}", flush=True)
    per = 150.0 / max(frames, 1)
    ref_s = f"{t_ref * per:.3f}" if ref is not None else "nan"
    speed = f"{t_ref / t_new:.2f}" if ref is not None else "nan"
    print(f"calls={len(jobs)} frames={frames} zero_flips={flips}")
    print(f"RESULT judge_s_per_150={t_new * per:.3f} reference_s_per_150={ref_s} "
          f"speedup={speed} max_abs_diff_m={diff:.3g}")


if __name__ == "__main__":
    main()
