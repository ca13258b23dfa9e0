"""Shape fit (Eq. 4): fit body shape (10 betas, optional global scale) to the robot's skeleton.

min_β,s,t  Σ_k w_k ‖s·R·J_k(β) + t − J_k^rob‖² + λ_β‖β‖²

Both skeletons are in their canonical T-pose (SMPL-X zero pose; the robot's `tpose` from its
definition). R is the fixed body→robot change of axes, t a free offset: together (R, s, t) map
the body's pelvis-rooted frame into the robot torso frame and are reused for every motion.
Results are cached per (robot, body model, settings) in memory and on disk.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.cache import cache_dir
from embody.config.ik import IKConfig
from embody.retarget.frames import BODY_TO_ROBOT
from embody.robot import Robot

_VERSION = 1
_MEMORY: dict[str, "ShapeFit"] = {}


@dataclass
class ShapeFit:
    """Fitted shape and the body→robot-torso map: p_robot = scale · rotation @ p_body + offset."""

    betas: np.ndarray
    scale: float
    rotation: np.ndarray
    offset: np.ndarray
    joint_names: list[str]
    residual_mm: np.ndarray
    robot: str
    body: str

    @property
    def mean_residual_mm(self) -> float:
        return float(self.residual_mm.mean())

    def apply(self, points: torch.Tensor) -> torch.Tensor:
        """Body-frame points (...,3) → robot torso frame."""
        r = torch.as_tensor(self.rotation, dtype=points.dtype, device=points.device)
        t = torch.as_tensor(self.offset, dtype=points.dtype, device=points.device)
        return self.scale * points @ r.T + t

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"betas": self.betas, "rotation": self.rotation, "offset": self.offset,
                "residual_mm": self.residual_mm}

    def to_attrs(self) -> dict[str, Any]:
        return {"scale": self.scale, "joint_names": list(self.joint_names), "robot": self.robot,
                "body": self.body, "mean_residual_mm": self.mean_residual_mm}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "ShapeFit":
        return cls(betas=np.asarray(arrays["betas"], dtype=np.float32), scale=float(attrs["scale"]),
                   rotation=np.asarray(arrays["rotation"], dtype=np.float64),
                   offset=np.asarray(arrays["offset"], dtype=np.float64),
                   joint_names=list(attrs["joint_names"]),
                   residual_mm=np.asarray(arrays["residual_mm"], dtype=np.float64),
                   robot=attrs["robot"], body=attrs["body"])


def _key(robot: Robot, body: BodyModel, cfg: IKConfig) -> str:
    settings = {k: getattr(cfg, k) for k in ("shape_iterations", "shape_lr", "shape_beta_reg", "shape_fit_scale")}
    blob = json.dumps({"v": _VERSION, "robot": robot.name, "spec": robot.spec.model_dump(mode="json"),
                       "body": body.name, "settings": settings}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def correspondences(robot: Robot, body: BodyModel) -> tuple[list[str], np.ndarray]:
    """SMPL-X joints the robot maps, with their fit weights."""
    names = [n for n in robot.spec.links if n in body.joint_names]
    weights = np.array([robot.spec.fit_weights.get(n, 1.0) for n in names])
    return names, weights


def fit(robot: Robot, body: BodyModel, cfg: IKConfig) -> ShapeFit:
    """Run the optimisation (deterministic: fixed init, full-batch Adam)."""
    names, weights = correspondences(robot, body)
    with torch.no_grad():
        q = torch.as_tensor(robot.tpose, dtype=torch.float64)[None]
        target, _ = robot.link_points(q, names)
    target = target[0]
    idx = [body.joint_index(n) for n in names]
    w = torch.as_tensor(weights / weights.sum(), dtype=torch.float64)
    rot = torch.as_tensor(BODY_TO_ROBOT, dtype=torch.float64)
    pose = body.tpose(1).to(torch.float64)

    betas = torch.zeros(10, dtype=torch.float64, requires_grad=True)
    log_scale = torch.zeros((), dtype=torch.float64, requires_grad=cfg.shape_fit_scale)
    offset = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    params = [betas, offset] + ([log_scale] if cfg.shape_fit_scale else [])
    opt = torch.optim.Adam(params, lr=cfg.shape_lr)

    def predict() -> torch.Tensor:
        joints = body.joints(pose, betas)[0, idx]
        return torch.exp(log_scale) * joints @ rot.T + offset

    with torch.no_grad():  # start with the offset that aligns the weighted centroids
        offset.copy_(((target - predict()) * w[:, None]).sum(0))
    for _ in range(cfg.shape_iterations):
        opt.zero_grad()
        err = ((predict() - target) ** 2).sum(-1)
        loss = (w * err).sum() + cfg.shape_beta_reg * (betas**2).sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        residual = torch.linalg.norm(predict() - target, dim=-1).numpy() * 1000.0
    return ShapeFit(betas=betas.detach().numpy().astype(np.float32), scale=float(torch.exp(log_scale.detach())),
                    rotation=BODY_TO_ROBOT.copy(), offset=offset.detach().numpy().copy(),
                    joint_names=names, residual_mm=residual, robot=robot.name, body=body.name)


def shape_fit(robot: Robot, body: BodyModel, cfg: IKConfig | None = None, *, use_cache: bool = True) -> ShapeFit:
    """The cached shape fit of `body` to `robot` (memory, then `$EMBODY_CACHE/shape_fit/`)."""
    cfg = cfg or IKConfig()
    key = _key(robot, body, cfg)
    if use_cache and key in _MEMORY:
        return _MEMORY[key]
    path = cache_dir() / "shape_fit" / f"{robot.name}-{body.name}-{key}.npz"
    if use_cache and path.is_file():
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k != "attrs"}
            attrs = json.loads(str(z["attrs"]))
        result = ShapeFit.from_arrays(arrays, attrs)
    else:
        result = fit(robot, body, cfg)
        if use_cache:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp, attrs=np.array(json.dumps(result.to_attrs())), **result.to_arrays())
            os.replace(tmp, path)
    if use_cache:
        _MEMORY[key] = result
    return result
