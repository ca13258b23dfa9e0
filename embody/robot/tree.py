"""NumPy forward kinematics of a body subset, straight from the MuJoCo model (`BodyFK` backend).

Walks only the bodies asked for (and their ancestors) with batched 3×3 products in float64, one
step per tree depth, and gives the same numbers as `mujoco.mj_kinematics` and the
pytorch-kinematics backend (tested). Transforms are in the robot torso frame, root fixed at its
default pose (as `Robot.body_transforms`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.robot.fk import BodyFK


def _axis_rotations(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rodrigues: rotations (T,J,3,3) by `angles` (T,J) about the unit `axes` (J,3)."""
    z = np.zeros(len(axes))
    k = np.stack([np.stack([z, -axes[:, 2], axes[:, 1]], -1), np.stack([axes[:, 2], z, -axes[:, 0]], -1),
                  np.stack([-axes[:, 1], axes[:, 0], z], -1)], -2)  # (J,3,3) cross-product matrices
    s, c = np.sin(angles)[..., None, None], np.cos(angles)[..., None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


class KinematicTree(BodyFK):
    """Batched NumPy FK of `bodies` (and their ancestors) for joint vectors in robot joint order."""

    def __init__(self, model: mujoco.MjModel, joint_names: list[str], base: np.ndarray,
                 bodies: list[str]) -> None:
        """`base`: 4×4 world → torso frame; the free joint stays at qpos0 (= the MJCF body pose)."""
        super().__init__(model, joint_names, bodies)
        order = self.order
        self.local_pos = model.body_pos[order].copy()
        depth: list[int] = []
        for p in self.parent:
            depth.append(0 if p < 0 else depth[p] + 1)
        #: per depth: (bodies, their parents), so FK takes one batched step per level
        self.levels = [(np.flatnonzero(np.array(depth) == d), np.array(self.parent)[np.array(depth) == d])
                       for d in range(max(depth) + 1)]
        quat_rot = np.zeros((len(order), 9))
        for i, b in enumerate(order):
            mujoco.mju_quat2Mat(quat_rot[i], model.body_quat[b])
        self.local_rot = quat_rot.reshape(-1, 3, 3)
        self.root_rot, self.root_pos = base[:3, :3].copy(), base[:3, 3].copy()

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = len(q)
        # every body's parent-to-body rotation at once: fixed offset times its hinge rotations
        local = np.broadcast_to(self.local_rot, (t, *self.local_rot.shape)).copy()
        for k in range(max((len(h) for h in self.joints), default=0)):
            bodies = [i for i, h in enumerate(self.joints) if len(h) > k]
            joints = [self.joints[i][k][0] for i in bodies]
            axes = np.array([self.joints[i][k][1] for i in bodies])
            local[:, bodies] = local[:, bodies] @ _axis_rotations(axes, q[:, joints])
        rot = np.empty((t, len(self.order), 3, 3))
        pos = np.empty((t, len(self.order), 3))
        roots = self.levels[0][0]  # bodies hanging off the world, seen from the torso frame
        rot[:, roots] = self.root_rot @ local[:, roots]
        pos[:, roots] = self.root_pos + self.local_pos[roots] @ self.root_rot.T
        for bodies, parents in self.levels[1:]:  # one batched step per tree depth
            r_p = rot[:, parents]
            rot[:, bodies] = r_p @ local[:, bodies]
            pos[:, bodies] = pos[:, parents] + (r_p @ self.local_pos[bodies][..., None])[..., 0]
        return rot, pos
