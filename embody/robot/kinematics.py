"""Differentiable forward kinematics: a pytorch-kinematics chain built from MuJoCo's compiled model.

The frame tree is built here from the `MjModel` the robot already loaded, not with
pytorch-kinematics' `build_chain_from_mjcf`, whose faults this avoids:

* its joint-type map is keyed by `mjtJoint` members, which numpy joint types from mujoco>=3.12
  no longer hash equal to (`KeyError: np.int32(3)`); here the type is compared by value;
* it recompiles the MJCF with meshes resolved against the current directory;
* it parses offsets and axes into float32: here they are MuJoCo's float64 body poses and joint
  axes, so FK agrees with `mj_kinematics` to ~1e-15.

The chain is rooted at the robot's root body with its free joint dropped (the root sits at its
MJCF default pose, as MuJoCo with qpos0). pytorch-kinematics 0.10 applies a non-zero
`<joint pos>` without undoing it, so such models are refused (`check_joint_pivots`); Menagerie's
G1 and H1 have none. Joint limits always come from the MuJoCo model, not from the chain.

Joint order of every tensor is the robot's (MuJoCo qpos order without the free joint); the
chain's own order (depth first, children in body-id order) is mapped once at construction.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytorch_kinematics as pk
import torch
from pytorch_kinematics.frame import Frame, Joint, Link
from pytorch_kinematics.transforms import Transform3d

from embody.errors import ConfigError


def check_joint_pivots(model: mujoco.MjModel, where: str) -> None:
    """pytorch-kinematics mishandles non-zero hinge pivots: refuse instead of computing wrong FK."""
    for j in range(model.njnt):
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE and np.abs(model.jnt_pos[j]).max() > 1e-12:
            raise ConfigError(where, f"joint {model.joint(j).name!r} has a non-zero pos, "
                                     "which pytorch-kinematics 0.10 handles wrongly")


#: MuJoCo joint type (by value) -> pytorch-kinematics joint type; free and ball joints have none.
_JOINT_TYPES = {int(mujoco.mjtJoint.mjJNT_HINGE): "revolute", int(mujoco.mjtJoint.mjJNT_SLIDE): "prismatic"}


def _frame(model: mujoco.MjModel, body: int, keep: set[int], where: str, root: bool = False) -> Frame:
    """The pk frame of `body` and its descendants in `keep`, with MuJoCo's float64 body offset and
    joint axis (the root's own joint, the free one, is dropped)."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.body_quat[body])
    offset = np.eye(4)
    offset[:3, :3], offset[:3, 3] = rot.reshape(3, 3), model.body_pos[body]
    name = model.body(body).name
    link = Link(name, offset=Transform3d(matrix=torch.tensor(offset), dtype=torch.float64))
    njnt = int(model.body_jntnum[body])
    if root:
        joint = Joint()
    elif njnt == 0:
        joint = Joint(name + "_fixed_joint")
    elif njnt == 1:
        j = int(model.body_jntadr[body])
        kind = _JOINT_TYPES.get(int(model.jnt_type[j]))
        if kind is None:
            raise ConfigError(where, f"joint {model.joint(j).name!r}: only hinge and slide joints "
                                     "below the root body are supported")
        joint = Joint(model.joint(j).name, joint_type=kind, axis=model.jnt_axis[j].copy(),
                      dtype=torch.float64, limits=(model.jnt_range[j][0], model.jnt_range[j][1]))
    else:
        raise ConfigError(where, f"body {name!r} has {njnt} joints; one joint per body is supported")
    out = Frame(name, link=link, joint=joint)
    out.children = [_frame(model, c, keep, where) for c in range(body + 1, model.nbody)
                    if c in keep and int(model.body_parentid[c]) == body]
    return out


class Kinematics:
    """Batched FK of named links, root-frame transforms (B, L, 4, 4) in float64."""

    def __init__(self, mjcf_path: Path, model: mujoco.MjModel, root_body: str, joint_names: list[str]) -> None:
        self.model = model
        self.where = str(mjcf_path)
        self.root_id = model.body(root_body).id
        self.root = _frame(model, self.root_id, set(range(model.nbody)), self.where, root=True)
        self.chain = pk.Chain(self.root, dtype=torch.float64)
        chain_joints = self.chain.get_joint_parameter_names()
        missing = set(joint_names) ^ set(chain_joints)
        if missing:
            raise ConfigError(str(mjcf_path), f"chain/model joint mismatch: {sorted(missing)[:5]}")
        #: chain column i takes robot joint perm[i]
        self.perm = torch.tensor([joint_names.index(n) for n in chain_joints])
        self.dtype = torch.float64

    def subchain(self, bodies: list[str]) -> pk.Chain:
        """The chain cut down to `bodies` (a connected set holding the root): FK computes only them."""
        keep = {self.model.body(b).id for b in bodies}
        return pk.Chain(_frame(self.model, self.root_id, keep, self.where, root=True), dtype=torch.float64)

    def frame_indices(self, bodies: list[str]) -> torch.Tensor:
        return torch.tensor([self.chain.frame_to_idx[b] for b in bodies])

    def transforms(self, q: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """World (MJCF default root pose) transforms of `frames` for joints q (B, n) → (B, F, 4, 4).

        Differentiable in q (pk's analytic backward); keeps q's device.
        """
        if str(self.chain.device) != str(q.device):
            self.chain = self.chain.to(device=q.device)
        th = q[:, self.perm.to(q.device)].to(self.dtype)
        all_t = self.chain.forward_kinematics_tensor(th)  # (F_all, B, 4, 4)
        return all_t[frames.to(q.device)].transpose(0, 1)
