"""The `Robot`: MuJoCo model, joint tables, link map and differentiable kinematics in one place."""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import mujoco
import numpy as np
import torch

from embody.errors import ConfigError
from embody.robot.chain import ChainFK
from embody.robot.compiled import compiled_model
from embody.robot.exclusions import check_ignored_pairs, lift_unlisted_excludes
from embody.robot.fk import BodyFK
from embody.robot.kinematics import Kinematics, check_joint_pivots
from embody.robot.spec import RobotSpec
from embody.robot.tree import KinematicTree


def _match(name: str, patterns: list[str]) -> bool:
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


@dataclass
class Robot:
    """A loaded robot. Joint arrays follow MuJoCo's qpos order with the free joint left out.

    The *torso frame* (x forward, y left, z up) is the torso body's frame at the T-pose; it is
    fixed to the root, so waist motion is part of the solution and targets stay comparable.
    """

    name: str
    spec: RobotSpec
    mjcf_path: Path
    model: mujoco.MjModel
    joint_names: list[str]
    lower: np.ndarray
    upper: np.ndarray
    velocity_limits: np.ndarray
    tpose: np.ndarray
    rest: np.ndarray
    ik_mask: np.ndarray
    qpos_adr: np.ndarray

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def ik_joint_names(self) -> list[str]:
        return [n for n, m in zip(self.joint_names, self.ik_mask) if m]

    @property
    def waist_joint_names(self) -> list[str]:
        return [n for n in self.ik_joint_names if _match(n, self.spec.waist_joints)]

    @property
    def has_hands(self) -> bool:
        return bool(self.spec.hands)

    def joint_index(self, name: str) -> int:
        return self.joint_names.index(name)

    @cached_property
    def derived(self) -> dict:
        """Models and tables derived from this robot by other modules, built on first use and
        keyed by what built them (e.g. `contacts.collision_model`): they live as long as the
        robot, not in module dicts keyed by `id(robot)`, which a new robot may reuse."""
        return {}

    @cached_property
    def kinematics(self) -> Kinematics:
        """The pytorch-kinematics chain, built on first use (float64)."""
        return Kinematics(self.mjcf_path, self.model, self.spec.root_body, self.joint_names)

    # --- frames -------------------------------------------------------------------------

    def qpos(self, q: np.ndarray) -> np.ndarray:
        """Full MuJoCo qpos (root at its default pose) for joint values q (n,)."""
        qpos = self.model.qpos0.copy()
        qpos[self.qpos_adr] = q
        return qpos

    @cached_property
    def torso_from_world(self) -> np.ndarray:
        """4×4 transform world → torso frame at the T-pose (root at its default pose)."""
        data = mujoco.MjData(self.model)
        data.qpos[:] = self.qpos(self.tpose)
        mujoco.mj_kinematics(self.model, data)
        b = self.model.body(self.spec.torso_body).id
        t = np.eye(4)
        t[:3, :3] = data.xmat[b].reshape(3, 3)
        t[:3, 3] = data.xpos[b]
        return np.linalg.inv(t)

    def fk(self, bodies: list[str], backend: str = "tree", variable: list[int] | None = None) -> BodyFK:
        """FK of `bodies` (and ancestors) in the torso frame for the IK: `backend` is
        "pytorch_kinematics" (the pk chain, cut down to those bodies) or "tree" (NumPy).
        `variable`: the joints that change between calls (the pk chain then reuses the others' bodies)."""
        if backend == "pytorch_kinematics":
            return ChainFK(self.kinematics, self.model, self.joint_names, self.torso_from_world, bodies,
                           variable=variable)
        if backend == "tree":
            return KinematicTree(self.model, self.joint_names, self.torso_from_world, bodies)
        raise ConfigError("ik.kinematics", f"unknown kinematics backend {backend!r}")

    def link_poses(self, q: np.ndarray, links: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """NumPy `link_points`: positions (T,L,3) and rotations (T,L,3,3) in the torso frame."""
        refs = [self.spec.links[n] for n in links]
        fk = self.fk([r.body for r in refs])
        rot, pos = fk.forward(np.atleast_2d(np.asarray(q, dtype=np.float64)))
        idx = [fk.index[r.body] for r in refs]
        off = np.array([r.offset for r in refs])
        return pos[:, idx] + np.einsum("tlab,lb->tla", rot[:, idx], off), rot[:, idx]

    def link_points(self, q: torch.Tensor, links: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions (B,L,3) and rotations (B,L,3,3) of mapped links (SMPL-X names) in the torso frame."""
        refs = [self.spec.links[n] for n in links]
        return self.points_from(self.body_transforms(q, [r.body for r in refs]), links)

    def landmark_points(self, q: np.ndarray, names: list[str] | None = None
                        ) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Landmark positions (T,K,3) and palm normals (T,2,3) [left, right] in the torso frame
        (NumPy FK); `names` defaults to every landmark the robot defines."""
        names = list(self.spec.landmarks) if names is None else list(names)
        refs = [self.spec.landmarks[n] for n in names]
        normals = [self.spec.palm_normals[s] for s in ("left", "right") if s in self.spec.palm_normals]
        fk = self.fk(sorted({r.body for r in refs + normals}))
        rot, pos = fk.forward(np.atleast_2d(np.asarray(q, dtype=np.float64)))
        idx = [fk.index[r.body] for r in refs]
        pts = pos[:, idx] + np.einsum("tlab,lb->tla", rot[:, idx], np.array([r.offset for r in refs]))
        nidx = [fk.index[r.body] for r in normals]
        nrm = np.einsum("tlab,lb->tla", rot[:, nidx], np.array([r.offset for r in normals]).reshape(-1, 3))
        return pts, nrm, names

    @cached_property
    def body_scale(self) -> float:
        """Shoulder-landmark distance at the T-pose (m): normalises fidelity distances."""
        p, _, _ = self.landmark_points(self.tpose[None], ["left_shoulder", "right_shoulder"])
        return float(np.linalg.norm(p[0, 0] - p[0, 1]))

    def points_from(self, t: torch.Tensor, links: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Link points/rotations from transforms (B,L,4,4) of the links' bodies, in `links` order."""
        refs = [self.spec.links[n] for n in links]
        off = torch.tensor([r.offset for r in refs], dtype=t.dtype, device=t.device)
        rot = t[..., :3, :3]
        pos = t[..., :3, 3] + (rot @ off[..., None])[..., 0]
        return pos, rot

    def body_transforms(self, q: torch.Tensor, bodies: list[str]) -> torch.Tensor:
        """Torso-frame transforms (B,L,4,4) of bodies for joint values q (B,n)."""
        kin = self.kinematics
        t = kin.transforms(q, kin.frame_indices(bodies))
        base = torch.as_tensor(self.torso_from_world, dtype=t.dtype, device=t.device)
        return base @ t

    # --- joint helpers ------------------------------------------------------------------

    def hand_joint_names(self, side: str) -> list[str]:
        fingers = self.spec.hands.get(side, {})
        return [j for f in ("thumb", "index", "middle") for j in fingers.get(f, [])]

    def velocity_limit_of(self, name: str) -> float:
        for pattern, v in self.spec.velocity_limits.items():
            if fnmatch.fnmatchcase(name, pattern):
                return float(v)
        return float("inf")

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)


def build_robot(name: str, spec: RobotSpec, mjcf_path: Path, where: str) -> Robot:
    """Assemble a Robot from its spec and MJCF; every inconsistency is a ConfigError at `where`."""
    try:
        model = compiled_model(mjcf_path)
    except ValueError as exc:
        raise ConfigError(f"{where}:mjcf", f"MuJoCo cannot load {mjcf_path}: {exc}") from None
    check_joint_pivots(model, f"{where}:mjcf")
    hinge = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    if len(hinge) != sum(model.jnt_type != mujoco.mjtJoint.mjJNT_FREE):
        raise ConfigError(f"{where}:mjcf", "only hinge joints (plus one free root) are supported")
    names = [model.joint(j).name for j in hinge]
    limited = model.jnt_limited[hinge].astype(bool)
    rng = model.jnt_range[hinge]
    # Limits come from MuJoCo (pk reports (0,0) for unlimited joints); unlimited → ±π.
    lower = np.where(limited, rng[:, 0], -np.pi)
    upper = np.where(limited, rng[:, 1], np.pi)
    body_names = {model.body(b).name for b in range(model.nbody)}
    for key, ref in spec.links.items():
        if ref.body not in body_names:
            raise ConfigError(f"{where}:links.{key}.body", f"no body {ref.body!r} in {mjcf_path.name}")
    for key, ref in [*spec.landmarks.items(), *spec.palm_normals.items()]:
        if ref.body not in body_names:
            raise ConfigError(f"{where}:landmarks.{key}.body", f"no body {ref.body!r} in {mjcf_path.name}")
    for key in ("root_body", "torso_body"):
        if getattr(spec, key) not in body_names:
            raise ConfigError(f"{where}:{key}", f"no body {getattr(spec, key)!r} in {mjcf_path.name}")
    tpose = np.zeros(len(names))
    for jn, v in spec.tpose.items():
        if jn not in names:
            raise ConfigError(f"{where}:tpose.{jn}", "unknown joint")
        tpose[names.index(jn)] = v
    if np.any(tpose < lower) or np.any(tpose > upper):
        raise ConfigError(f"{where}:tpose", "T-pose outside the joint limits")
    rest = np.zeros(len(names))
    for jn, v in spec.rest.items():
        if jn not in names:
            raise ConfigError(f"{where}:rest.{jn}", "unknown joint")
        rest[names.index(jn)] = v
    rest = np.clip(rest, lower, upper)
    for side, fingers in spec.hands.items():
        for finger, joints in fingers.items():
            for jn in joints:
                if jn not in names:
                    raise ConfigError(f"{where}:hands.{side}.{finger}", f"unknown joint {jn!r}")
    check_ignored_pairs(model, spec, where)
    model = lift_unlisted_excludes(model, spec)
    ik_mask = np.array([_match(n, spec.ik_joints) for n in names])
    if not ik_mask.any():
        raise ConfigError(f"{where}:ik_joints", "matches no joint")
    robot = Robot(name=name, spec=spec, mjcf_path=mjcf_path, model=model, joint_names=names,
                  lower=lower, upper=upper, velocity_limits=np.zeros(len(names)), tpose=tpose, rest=rest,
                  ik_mask=ik_mask, qpos_adr=model.jnt_qposadr[hinge].copy())
    robot.velocity_limits = np.array([robot.velocity_limit_of(n) for n in names])
    return robot
