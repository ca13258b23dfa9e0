"""Differentiable forward kinematics: a pytorch-kinematics chain built from the MJCF.

`build_chain_from_mjcf` (pytorch-kinematics 0.10) needs a small adapter, documented here:

* mujoco is pinned below 3.12 (its joint-type map breaks on newer enums): done in pyproject.
* The robot has a free joint, so the chain is rooted at `body=<root body>`; the free joint is
  dropped and the root sits at its MJCF default pose (as MuJoCo with qpos0).
* Mesh files would resolve against the current directory (fix: `assets=` bytes). The chain needs
  only the kinematic tree, so we strip mesh geoms and mesh assets from the XML instead, which
  also skips MuJoCo's mesh compilation (≈3 s for G1); the MJCF's `<inertial>` keeps it valid.
* Unlimited joints get (0, 0) limits there: limits always come from the MuJoCo model instead.
* A non-zero `<joint pos>` gives wrong FK (the pivot offset is applied but never undone): we
  refuse such models with a ConfigError. Menagerie's G1 and H1 have none (checked at load).
* Link offsets and axes are parsed into float32 `Transform3d`s, so even a float64 chain is off
  by ~4e-8 m: they are re-seated from the MuJoCo model in float64 (FK then agrees with
  `mj_kinematics` to ~1e-15). Sites (never used) are dropped on the way.

Joint order of every tensor is the robot's (MuJoCo qpos order without the free joint); the
chain's own order is mapped once at construction.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytorch_kinematics as pk
import torch
from pytorch_kinematics.frame import Frame, Joint, Link
from pytorch_kinematics.transforms import Transform3d

from embody.errors import ConfigError


def _tree_only_xml(mjcf_path: Path) -> str:
    """The MJCF without meshes: bodies, joints and primitive geoms only."""
    root = ET.parse(mjcf_path).getroot()
    for parent in root.iter():
        for child in list(parent):
            if child.tag == "mesh" or (child.tag == "geom" and "mesh" in child.attrib):
                parent.remove(child)
    return ET.tostring(root, encoding="unicode")


def check_joint_pivots(model: mujoco.MjModel, where: str) -> None:
    """pytorch-kinematics mishandles non-zero hinge pivots: refuse instead of computing wrong FK."""
    for j in range(model.njnt):
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE and np.abs(model.jnt_pos[j]).max() > 1e-12:
            raise ConfigError(where, f"joint {model.joint(j).name!r} has a non-zero pos, "
                                     "which pytorch-kinematics 0.10 handles wrongly")


def _seat(frame: Frame, model: mujoco.MjModel, keep: set[str]) -> Frame:
    """A copy of pk's frame tree with MuJoCo's float64 body offsets and joint axes, restricted to
    the bodies in `keep` (sites, never in it, are left out)."""
    b = model.body(frame.name).id
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.body_quat[b])
    offset = np.eye(4)
    offset[:3, :3], offset[:3, 3] = rot.reshape(3, 3), model.body_pos[b]
    link = Link(frame.name, offset=Transform3d(matrix=torch.tensor(offset), dtype=torch.float64))
    joint = frame.joint
    if joint.joint_type != "fixed":
        j = model.joint(joint.name).id
        joint = Joint(joint.name, joint_type=joint.joint_type, axis=model.jnt_axis[j].copy(),
                      dtype=torch.float64, limits=joint.limits)
    out = Frame(frame.name, link=link, joint=joint)
    out.children = [_seat(c, model, keep) for c in frame.children if c.name in keep]
    return out


class Kinematics:
    """Batched FK of named links, root-frame transforms (B, L, 4, 4) in float64."""

    def __init__(self, mjcf_path: Path, model: mujoco.MjModel, root_body: str, joint_names: list[str]) -> None:
        parsed = pk.build_chain_from_mjcf(_tree_only_xml(mjcf_path), body=root_body)
        self.model = model
        self.root = _seat(parsed._root, model, {model.body(b).name for b in range(model.nbody)})
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
        return pk.Chain(_seat(self.root, self.model, set(bodies)), dtype=torch.float64)

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
