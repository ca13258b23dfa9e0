"""Forward kinematics of a body subset for the IK: one interface, two backends.

The IK needs, per iteration and for every frame at once, the torso-frame rotations and positions
of a few dozen bodies, plus each joint's axis and pivot for geometric Jacobians. `BodyFK` holds
the body subset (the bodies asked for and their ancestors, in MuJoCo order) and derives joint
frames and masks from any backend's `forward`; backends only compute transforms:
`embody.robot.tree.KinematicTree` (NumPy) and `embody.robot.chain.ChainFK` (pytorch-kinematics).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import mujoco
import numpy as np


class BodyFK(ABC):
    """Torso-frame FK of `bodies` (and their ancestors) for joint vectors in robot joint order.

    Joint pivots are body origins: hinge `pos` is zero on every loaded robot (`check_joint_pivots`).
    """

    def __init__(self, model: mujoco.MjModel, joint_names: list[str], bodies: list[str]) -> None:
        ids: set[int] = set()
        for name in bodies:
            b = model.body(name).id
            while b > 0 and b not in ids:
                ids.add(b)
                b = int(model.body_parentid[b])
        order = sorted(ids)  # MuJoCo numbers parents before children
        #: MuJoCo body ids of the walked bodies; outputs index bodies in this order
        self.order = order
        self.names = [model.body(b).name for b in order]
        self.index = {name: i for i, name in enumerate(self.names)}
        self.parent = [order.index(int(model.body_parentid[b])) if model.body_parentid[b] in ids else -1
                       for b in order]
        #: per body: (robot joint index, local axis) of its hinges, in MuJoCo order
        self.joints: list[list[tuple[int, np.ndarray]]] = []
        for b in order:
            hinges = []
            for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                    hinges.append((joint_names.index(model.joint(j).name), model.jnt_axis[j].copy()))
            self.joints.append(hinges)

    @abstractmethod
    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (T,B,3,3) and positions (T,B,3), float64, of every walked body for q (T, n_joints)."""

    def forward_once(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`forward` for a one-off batch: it leaves any state a backend keeps between calls (and
        so the rounding of the next `forward`) as it was."""
        return self.forward(q)

    def joint_frames(self, rot: np.ndarray, pos: np.ndarray, joints: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """World axes (T,J,3) and pivots (T,J,3) of robot joints `joints` (pivots are body origins)."""
        key = tuple(joints)
        cache = self.__dict__.setdefault("_frames_of", {})
        if key not in cache:  # the lookup tables, once per joint set (every IK Jacobian asks)
            where = {j: (i, axis) for i, hinges in enumerate(self.joints) for j, axis in hinges}
            cache[key] = (np.array([where[j][0] for j in joints], dtype=np.int64),
                          np.array([where[j][1] for j in joints]))
        body, axes = cache[key]
        return np.einsum("tjab,jb->tja", rot[:, body], axes), pos[:, body]

    def moves(self, joints: list[int]) -> np.ndarray:
        """mask (J, B): joint j moves body b (j sits on b or one of its ancestors)."""
        where = {j: i for i, hinges in enumerate(self.joints) for j, _ in hinges}
        mask = np.zeros((len(joints), len(self.order)))
        for b in range(len(self.order)):
            p = b
            while p >= 0:
                for k, j in enumerate(joints):
                    if where.get(j) == p:
                        mask[k, b] = 1.0
                p = self.parent[p]
        return mask


def rotate(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """r @ v for stacks of 3×3 matrices r (...,3,3) and vectors v (...,3) (broadcast): the three
    columns summed, ~2× faster than numpy's batched matmul of 3×3 by 3×1."""
    return r[..., 0] * v[..., 0, None] + r[..., 1] * v[..., 1, None] + r[..., 2] * v[..., 2, None]
