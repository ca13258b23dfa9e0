"""CPU cost of one collision-optimiser step, by part, on one sequence's whole motion.

Replays what `embody.collision.optimize._optimise` does per Adam step (FK with autograd, the
broad-phase refresh every `refresh_every` steps, the clearance energy on the refreshed
candidates, the capsule term, backward) at a fixed perturbed pose, so the per-step cost can be
compared between checkouts without the step count (which moves with any change) mixing in.

    python benchmarks/collision_step.py [--data DIR] [--seq 0] [--steps 20]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from embody.body import MannequinBody
from embody.collision.capsules import arm_capsules, capsule_energies
from embody.collision.energy import collision_model, contacts, frame_energies
from embody.collision.masks import mask_joints
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--seq", type=int, default=0)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = CollisionConfig()
    body = MannequinBody()
    motion = load(sorted(default_dataset(args.data).glob("seq_*.npz"))[args.seq])
    model = collision_model(body, motion.betas, vertex_stride=cfg.contact_stride,
                            allow_pairs=cfg.allow_pairs, max_overfill=cfg.max_overfill)
    x0 = torch.as_tensor(motion.pose, dtype=torch.float32)
    betas = torch.as_tensor(motion.betas, dtype=torch.float32)
    idx = torch.as_tensor(mask_joints(cfg.mask, cfg.joints))
    u = torch.full((len(x0), len(idx), 3), 0.01, requires_grad=True)
    caps = arm_capsules(body, motion.betas, cfg.allow_pairs)
    margin = cfg.refresh_margin + cfg.clearance
    parts = dict.fromkeys(("fk", "refresh", "energy", "capsules", "backward"), 0.0)
    near = None
    for step in range(args.steps + 2):  # the first two warm up
        marks = [time.process_time()]
        x = x0 + torch.zeros_like(x0).index_copy(1, idx, u)
        tr = body.joint_transforms(x, betas)
        marks.append(time.process_time())
        if step % cfg.refresh_every == 0:
            td = tr.detach()
            near = contacts(model, td, margin)
            frame_energies(model, td, cfg.tolerance, near)
        marks.append(time.process_time())
        e = frame_energies(model, tr, cfg.tolerance - cfg.clearance, near)
        marks.append(time.process_time())
        e = e + cfg.capsule_weight * capsule_energies(caps, tr)
        marks.append(time.process_time())
        (e.sum() + cfg.lambda_close * (x - x0).square().sum()).backward()
        marks.append(time.process_time())
        if step >= 2:
            for k, a, b in zip(parts, marks[:-1], marks[1:]):
                parts[k] += (b - a) * 1e3 / args.steps
    print("RESULT " + " ".join(f"{k}_ms={v:.2f}" for k, v in parts.items())
          + f" step_ms={sum(parts.values()):.2f} frames={len(x0)} seq={args.seq}")


if __name__ == "__main__":
    main()
