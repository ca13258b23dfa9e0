"""Synthetic dataset generation and motion I/O speed, with the artifact mix it produces.

Prints one row per sequence, then `RESULT ...`. Run: python benchmarks/synth_io.py [--n 24]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from embody.io import load, save
from embody.synth.artifacts import PENETRATIONS
from embody.synth.generator import generate_sequence
from embody.synth.kinematics import ArmIK


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    t0 = time.perf_counter()
    ik = ArmIK()
    setup = time.perf_counter() - t0
    gen_s, load_s, save_s, frames, pen, ik_err = [], [], [], 0, 0, []
    with tempfile.TemporaryDirectory() as tmp:
        for index in range(args.n):
            t = time.perf_counter()
            motion = generate_sequence(args.seed, index, ik)
            gen_s.append(time.perf_counter() - t)
            path = Path(tmp) / f"seq_{index:03d}.npz"
            t = time.perf_counter()
            save(motion, path)
            save_s.append(time.perf_counter() - t)
            t = time.perf_counter()
            back = load(path)
            load_s.append(time.perf_counter() - t)
            assert np.array_equal(back.pose, motion.pose)
            kinds = [a["kind"] for a in motion.meta["artifacts"]]
            pen += any(k in PENETRATIONS for k in kinds)
            frames += motion.num_frames
            ik_err.append(motion.meta["ik_error_max_m"])  # worst keyframe wrist miss
            print(f"seq={index:03d} frames={motion.num_frames} gen_ms={gen_s[-1] * 1e3:.0f} "
                  f"save_ms={save_s[-1] * 1e3:.1f} load_ms={load_s[-1] * 1e3:.1f} "
                  f"signs={len(motion.meta['gloss'])} ik_err_mm={ik_err[-1] * 1e3:.2f} artifacts={','.join(kinds) or 'clean'}")
    print(f"RESULT n={args.n} setup_s={setup:.2f} gen_total_s={sum(gen_s):.2f} "
          f"gen_ms_per_seq={1e3 * np.mean(gen_s):.0f} frames_per_s={frames / sum(gen_s):.0f} "
          f"save_ms_per_seq={1e3 * np.mean(save_s):.1f} load_ms_per_seq={1e3 * np.mean(load_s):.1f} "
          f"ik_err_max_mm={1e3 * max(ik_err):.2f} with_penetration={pen}/{args.n}")


if __name__ == "__main__":
    main()
