"""pytorch-kinematics forward kinematics of a body subset (`BodyFK` backend).

The robot's pk chain (`Robot.kinematics`, float64) is cut down to the walked bodies, so one
batched `forward_kinematics_tensor` call per IK iteration computes exactly the frames the solver
uses, for every frame of the sequence at once. That call is the batched core of
`Chain.forward_kinematics`, without wrapping each link in a `Transform3d` (which doubles the
time on G1). The solver stays NumPy: q goes in and transforms come out through
zero-copy views on the CPU; on another device only these two transfers cross it.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from embody.robot.fk import BodyFK
from embody.robot.kinematics import Kinematics


class ChainFK(BodyFK):
    """Batched pytorch-kinematics FK of `bodies` (and their ancestors) in the torso frame."""

    def __init__(self, kinematics: Kinematics, model: mujoco.MjModel, joint_names: list[str],
                 base: np.ndarray, bodies: list[str], device: torch.device | str = "cpu") -> None:
        """`base`: 4×4 world → torso frame; the free joint stays at qpos0 (= the MJCF body pose)."""
        super().__init__(model, joint_names, bodies)
        self.device = torch.device(device)
        self.chain = kinematics.subchain(self.names).to(device=self.device)
        #: chain column i takes robot joint cols[i]; frames[b] is walked body b's chain frame
        self.cols = torch.tensor([joint_names.index(n) for n in self.chain.get_joint_parameter_names()],
                                 device=self.device)
        self.frames = torch.tensor([self.chain.frame_to_idx[n] for n in self.names], device=self.device)
        base_t = torch.as_tensor(base, dtype=torch.float64, device=self.device)
        self.base_rot, self.base_pos = base_t[:3, :3], base_t[:3, 3]

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.no_grad():
            th = torch.as_tensor(q, dtype=torch.float64).to(self.device)[:, self.cols]
            t = self.chain.forward_kinematics_tensor(th)[self.frames].transpose(0, 1)  # (T,B,4,4)
            rot = self.base_rot @ t[..., :3, :3]
            pos = t[..., :3, 3] @ self.base_rot.T + self.base_pos
        return rot.cpu().numpy(), pos.cpu().numpy()
