"""Masked test-time optimisation (Eq. 2–3): push penetrating parts apart, stay close and smooth.

x_eff = x0 + M ⊙ (x − x0); minimise with Adam
    λ_col L_col(x_eff) + λ_close ‖x_eff − x0‖² + λ_smooth ‖Δ²x_eff‖²
(the last two as means over frames, like L_col). Only the masked joints are parameters, so
unmasked joints are x0 bit for bit. The optimised L_col also counts points within `clearance`
outside a part, so a strong closeness pull settles with the surfaces apart rather than at
residual depth. The broad phase is refreshed every few steps with a margin; the energies
reported before and after are always exact, at `tolerance`.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.collision.energy import CollisionModel, collision_model, contacts, frame_energies
from embody.collision.masks import mask_joints
from embody.collision.metrics import sequence_metrics
from embody.config.collision import CollisionConfig
from embody.motion import Motion


@dataclass
class CollisionResult:
    """The fixed motion, per-frame energies before/after and the paper's metrics."""

    motion: Motion
    metrics: dict[str, Any]
    frame_energy_before: np.ndarray
    frame_energy_after: np.ndarray
    mask: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {f"motion_{k}": v for k, v in self.motion.to_arrays().items()}
        arrays.update(frame_energy_before=self.frame_energy_before,
                      frame_energy_after=self.frame_energy_after, mask=self.mask)
        return arrays

    def to_attrs(self) -> dict[str, Any]:
        return {"metrics": dict(self.metrics), "motion": self.motion.to_attrs()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "CollisionResult":
        motion = Motion.from_arrays({k[len("motion_"):]: np.asarray(v) for k, v in arrays.items()
                                     if k.startswith("motion_")}, attrs["motion"])
        return cls(motion=motion, metrics=dict(attrs["metrics"]),
                   frame_energy_before=np.asarray(arrays["frame_energy_before"]),
                   frame_energy_after=np.asarray(arrays["frame_energy_after"]),
                   mask=np.asarray(arrays["mask"]))


def model_for(body: BodyModel, motion: Motion, cfg: CollisionConfig) -> CollisionModel:
    return collision_model(body, motion.betas, vertex_stride=cfg.vertex_stride,
                           allow_pairs=cfg.allow_pairs, max_overfill=cfg.max_overfill)


def _energies(body: BodyModel, model: CollisionModel, pose: torch.Tensor, betas: torch.Tensor,
              tolerance: float) -> torch.Tensor:
    return frame_energies(model, body.joint_transforms(pose, betas), tolerance)


def frame_collision_energies(motion: Motion, body: BodyModel,
                             cfg: CollisionConfig | None = None) -> np.ndarray:
    """Per-frame Σ_v max(0, −f)² (T,) of a motion, float64."""
    cfg = cfg or CollisionConfig()
    pose = torch.as_tensor(motion.pose, dtype=torch.float64)
    with torch.no_grad():
        e = _energies(body, model_for(body, motion, cfg), pose,
                      torch.as_tensor(motion.betas, dtype=torch.float64), cfg.tolerance)
    return e.numpy()


def collision_energy(motion: Motion, body: BodyModel, cfg: CollisionConfig | None = None) -> float:
    """L_col (Eq. 1) of a motion: the mean of its per-frame energies."""
    return float(frame_collision_energies(motion, body, cfg).mean())


def _second_diff(x: torch.Tensor) -> torch.Tensor:
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


@contextmanager
def _threads(n: int) -> Iterator[None]:
    """Torch intra-op threads for the duration of one optimisation (process-wide setting)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def mitigate(motion: Motion, body: BodyModel,
             cfg: CollisionConfig | None = None) -> CollisionResult:
    """Reduce self-collision of `motion` by moving only the masked joints (Eq. 2–3)."""
    cfg = cfg or CollisionConfig()
    with _threads(cfg.threads):
        return _mitigate(motion, body, cfg)


def _mitigate(motion: Motion, body: BodyModel, cfg: CollisionConfig) -> CollisionResult:
    start = time.perf_counter()
    idx = mask_joints(cfg.mask, cfg.joints)
    model = model_for(body, motion, cfg)
    before = frame_collision_energies(motion, body, cfg)
    x0_np = motion.pose
    best_pose, steps = x0_np, 0
    if cfg.enabled and before.mean() > 0 and cfg.steps > 0:
        best_pose, steps = _optimise(body, model, motion, idx, cfg)
    fixed = motion.with_pose(best_pose)
    after = before if steps == 0 else frame_collision_energies(fixed, body, cfg)
    if after.mean() > before.mean():  # never hand back something worse than the input
        fixed, after = motion.with_pose(x0_np), before
    runtime = time.perf_counter() - start
    metrics = sequence_metrics(x0_np, fixed.pose, float(before.mean()), float(after.mean()),
                               runtime, steps)
    metrics["mask"] = cfg.mask
    return CollisionResult(fixed, metrics, before, after, idx)


def _optimise(body: BodyModel, model: CollisionModel, motion: Motion, idx: np.ndarray,
              cfg: CollisionConfig) -> tuple[np.ndarray, int]:
    """Adam over the masked joints; returns the best pose seen (lowest energy, then objective)."""
    x0 = torch.as_tensor(motion.pose, dtype=torch.float32)
    betas = torch.as_tensor(motion.betas, dtype=torch.float32)
    t = x0.shape[0]
    jidx = torch.as_tensor(idx)
    params = x0[:, jidx].clone().requires_grad_(True)
    opt = torch.optim.Adam([params], lr=cfg.lr)
    best = (float("inf"), float("inf"))
    best_pose = x0.numpy().copy()
    prev_obj, calm, step, near, last_gain, e_first = None, 0, 0, None, 0, 0.0
    for step in range(1, cfg.steps + 1):
        x = x0.index_copy(1, jidx, params)
        transforms = body.joint_transforms(x, betas)
        if (step - 1) % cfg.refresh_every == 0:
            near = contacts(model, transforms.detach(), cfg.refresh_margin + cfg.clearance)
        e = frame_energies(model, transforms, cfg.tolerance - cfg.clearance, near).mean()
        close = ((x - x0) ** 2).sum() / t
        smooth = (_second_diff(x) ** 2).sum() / t
        obj = cfg.lambda_col * e + cfg.lambda_close * close + cfg.lambda_smooth * smooth
        e_val, o_val = float(e.detach()), float(obj.detach())
        if step == 1:
            e_first = e_val  # progress is measured relative to the starting energy
        if (e_val, o_val) < best:
            if step == 1 or e_val < best[0] - cfg.early_stop_rtol * e_first:
                last_gain = step
            best, best_pose = (e_val, o_val), x.detach().numpy().copy()
        if cfg.early_stop and step - last_gain >= cfg.early_stop_stall:
            break  # the energy stopped falling: a residual the mask cannot resolve
        if cfg.early_stop and e_val == 0.0:
            calm = calm + 1 if prev_obj is not None and \
                abs(prev_obj - o_val) <= cfg.early_stop_rtol * max(abs(o_val), 1e-12) else 0
            if calm >= cfg.early_stop_patience:
                break
        else:
            calm = 0
        prev_obj = o_val
        opt.zero_grad(set_to_none=True)
        obj.backward()
        opt.step()
    return best_pose, step
