"""Per-frame retargeting targets in the robot torso frame, built from the fitted body.

The body is evaluated with the fitted betas and its root rotation and translation removed, so
targets follow the signer's upper body relative to the pelvis, whatever the camera frame.
Positions map through the shape fit (p_robot = s·R·p_body + t).

Orientation offset (calibrated at the T-pose): in the SMPL-X zero pose every joint's global
rotation is the identity, so a human link rotated by G(t) (body frame) maps to the robot link
rotation  R · G(t) · Rᵀ · R_link^tpose , where R is the body→robot change of axes and
R_link^tpose the robot link's rotation at its T-pose (torso frame). At the T-pose the target is
exactly the robot's T-pose orientation: palms down on both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.motion import Motion
from embody.retarget.hands import retarget_hands
from embody.retarget.shape_fit import ShapeFit
from embody.robot import Robot

_ARRAYS = ("wrist_pos", "wrist_rot", "elbow_pos", "torso_rot", "head_rot", "hand_q")


@dataclass
class Targets:
    """wrist_pos (T,2,3) [left, right], wrist_rot (T,2,3,3), elbow_pos (T,2,3),
    torso_rot / head_rot (T,3,3), hand_q (T,H) for `hand_joints`, all in the robot torso frame."""

    wrist_pos: np.ndarray
    wrist_rot: np.ndarray
    elbow_pos: np.ndarray
    torso_rot: np.ndarray
    head_rot: np.ndarray
    hand_q: np.ndarray
    hand_joints: list[str]
    fps: float
    #: Robot shoulder→elbow→wrist length (m), to normalise errors.
    arm_length: float

    @property
    def num_frames(self) -> int:
        return int(self.wrist_pos.shape[0])

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in _ARRAYS}

    def to_attrs(self) -> dict[str, Any]:
        return {"hand_joints": list(self.hand_joints), "fps": self.fps, "arm_length": self.arm_length}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "Targets":
        return cls(**{k: np.asarray(arrays[k]) for k in _ARRAYS}, hand_joints=list(attrs["hand_joints"]),
                   fps=float(attrs["fps"]), arm_length=float(attrs["arm_length"]))


def robot_arm_length(robot: Robot) -> float:
    q = torch.as_tensor(robot.tpose)[None]
    with torch.no_grad():
        p, _ = robot.link_points(q, ["left_shoulder", "left_elbow", "left_wrist"])
    p = p[0].numpy()
    return float(np.linalg.norm(p[1] - p[0]) + np.linalg.norm(p[2] - p[1]))


def tpose_rotations(robot: Robot, links: list[str]) -> np.ndarray:
    with torch.no_grad():
        _, r = robot.link_points(torch.as_tensor(robot.tpose)[None], links)
    return r[0].numpy()


def build_targets(motion: Motion, body: BodyModel, fit: ShapeFit, robot: Robot) -> Targets:
    """Targets for every frame of `motion` (its hands must be absolute, as `Motion` guarantees)."""
    pose = torch.as_tensor(motion.pose, dtype=torch.float64).clone()
    pose[:, 0] = 0.0  # root rotation: targets are relative to the pelvis
    betas = torch.as_tensor(fit.betas, dtype=torch.float64)
    with torch.no_grad():
        transforms = body.joint_transforms(pose, betas)
    pos = fit.apply(transforms[..., :3, 3]).numpy()
    rot = transforms[..., :3, :3].numpy()
    axes = fit.rotation

    def idx(name: str) -> int:
        return body.joint_index(name)

    def mapped_rot(joint: str, link: str) -> np.ndarray:
        rest = tpose_rotations(robot, [link])[0]
        return axes @ rot[:, idx(joint)] @ axes.T @ rest

    sides = ("left", "right")
    identity = np.tile(np.eye(3), (len(pos), 1, 1))
    hand_q, hand_joints = retarget_hands(motion.pose, robot)
    return Targets(
        wrist_pos=np.stack([pos[:, idx(f"{s}_wrist")] for s in sides], axis=1),
        wrist_rot=np.stack([mapped_rot(f"{s}_wrist", f"{s}_wrist") for s in sides], axis=1),
        elbow_pos=np.stack([pos[:, idx(f"{s}_elbow")] for s in sides], axis=1),
        torso_rot=mapped_rot("spine3", "spine3") if "spine3" in robot.spec.links else identity,
        head_rot=mapped_rot("head", "head") if "head" in robot.spec.links else identity,
        hand_q=hand_q, hand_joints=hand_joints, fps=motion.fps, arm_length=robot_arm_length(robot),
    )
