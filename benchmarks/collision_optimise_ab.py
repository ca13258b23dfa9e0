"""Adam's collision optimiser alone (`optimize._optimise`), A/B: a reference `optimize.py` on a
reference `energy.py` (e.g. `git show <rev>:embody/collision/optimize.py`) against the current
code, back to back in one process on the same inputs (the contact-stride model, the blend
weights of the input's penetrating frames), so both share the machine's load.

CPU seconds (`time.process_time`, one torch thread) per 150 frames of each, with steps and the
largest pose difference per sequence (0 when the optimiser's poses are bit for bit). Each side
runs once untimed on `--warmup` first (compiled kernels, model caches). Ends with one `RESULT`
line.

    python benchmarks/collision_optimise_ab.py --ref /tmp/ref_opt.py --ref-energy /tmp/ref_energy.py
        [--seqs 3 21 0 13] [--warmup 17]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from embody.body import MannequinBody
from embody.collision import optimize
from embody.collision.energy import collision_model
from embody.collision.masks import mask_joints
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset
from _reference import load_reference  # benchmarks/, the script's own folder

ROOT = Path(__file__).resolve().parents[1]


def _inputs(body, motion, cfg):
    """What `mitigate` hands `_optimise`: the contact-stride model and the blend weights."""
    model = collision_model(body, motion.betas, vertex_stride=cfg.contact_stride,
                            allow_pairs=cfg.allow_pairs, max_overfill=cfg.max_overfill)
    before = optimize._exact(body, model, motion.pose, motion.betas, cfg.tolerance)
    weight = optimize.blend_weights(before > 0, int(round(cfg.blend_s * motion.fps)))
    return model, mask_joints(cfg.mask, cfg.joints), weight


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--ref", required=True, help="path of the reference optimize.py")
    ap.add_argument("--ref-energy", required=True, help="path of the reference energy.py")
    ap.add_argument("--seqs", type=int, nargs="+", default=[3, 21, 0, 13])
    ap.add_argument("--warmup", type=int, default=17, metavar="SEQ")
    args = ap.parse_args()
    torch.set_num_threads(1)
    current = sys.modules["embody.collision.energy"]
    sys.modules["embody.collision.energy"] = ref_energy = load_reference(args.ref_energy,
                                                                         "energy_ref")
    try:
        ref = load_reference(args.ref, "optimize_ref")
    finally:
        sys.modules["embody.collision.energy"] = current
    body, cfg = MannequinBody(), CollisionConfig()
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))
    cpu_ref = cpu_new = 0.0
    frames = 0
    for n, i in enumerate([args.warmup, *args.seqs]):
        m = load(paths[i])
        model, idx, weight = _inputs(body, m, cfg)
        ref_model = ref_energy.collision_model(body, m.betas, vertex_stride=cfg.contact_stride,
                                               allow_pairs=cfg.allow_pairs,
                                               max_overfill=cfg.max_overfill)
        t0 = time.process_time()
        pa, sa = ref._optimise(body, ref_model, m, idx, weight, cfg)
        t1 = time.process_time()
        pb, sb = optimize._optimise(body, model, m, idx, weight, cfg)
        t2 = time.process_time()
        if n == 0:  # the warm-up: not timed
            continue
        cpu_ref, cpu_new, frames = cpu_ref + t1 - t0, cpu_new + t2 - t1, frames + len(m.pose)
        diff = float(np.abs(pa - pb).max())
        print(f"seq_{i:03d} T={len(m.pose)} ref {t1 - t0:.2f}s steps={sa} "
              f"({(t1 - t0) / sa * 1e3:.1f} ms/step) | new {t2 - t1:.2f}s steps={sb} "
              f"({(t2 - t1) / sb * 1e3:.1f} ms/step) max_pose_diff={diff:.2e}", flush=True)
    print(f"RESULT ref_optimise_cpu_per_150_frames={cpu_ref / frames * 150:.2f} "
          f"new_optimise_cpu_per_150_frames={cpu_new / frames * 150:.2f} "
          f"speedup={cpu_ref / cpu_new:.2f} frames={frames}")


if __name__ == "__main__":
    main()
