"""pytorch-kinematics forward kinematics of a body subset (`BodyFK` backend).

The robot's pk chain (`Robot.kinematics`, float64) is cut down to the walked bodies, so one
batched `forward_kinematics_tensor` call per IK iteration computes exactly the frames the solver
uses, for every frame of the sequence at once. That call is the batched core of
`Chain.forward_kinematics`, without wrapping each link in a `Transform3d` (which doubles the
time on G1). The solver stays NumPy: q goes in and transforms come out through
zero-copy views on the CPU; on another device only these two transfers cross it.

Given the joints that vary between calls (`variable`: the IK's), bodies below the last of them
(the fingers, at each frame's retargeted handshape) or off their path (the pinned legs) are not
evaluated by the chain: their transforms relative to their nearest ancestor carrying a variable
joint (absolute where there is none) are kept from a full pass and reused while the other
joints' values stay the same (checked on every call). The chain then evaluates 18 of G1's 38
walked bodies.
"""

from __future__ import annotations

import threading

import mujoco
import numpy as np
import torch

from embody.robot.fk import BodyFK, rotate
from embody.robot.kinematics import Kinematics


class ChainFK(BodyFK):
    """Batched pytorch-kinematics FK of `bodies` (and their ancestors) in the torso frame."""

    def __init__(self, kinematics: Kinematics, model: mujoco.MjModel, joint_names: list[str],
                 base: np.ndarray, bodies: list[str], device: torch.device | str = "cpu",
                 variable: list[int] | None = None) -> None:
        """`base`: 4×4 world → torso frame; the free joint stays at qpos0 (= the MJCF body pose).
        `variable`: robot joint indices that change between calls (None: any may)."""
        super().__init__(model, joint_names, bodies)
        self.device = torch.device(device)
        self.chain, self.cols, self.frames = self._subchain(kinematics, self.names, joint_names)
        base_t = torch.as_tensor(base, dtype=torch.float64, device=self.device)
        self.base_rot, self.base_pos = base_t[:3, :3], base_t[:3, 3]
        #: the torso frame is often the world frame shifted (G1): then no rotation is applied
        self.base_shift = (np.asarray(base, dtype=np.float64)[:3, 3]
                           if np.array_equal(np.asarray(base)[:3, :3], np.eye(3)) and self.device.type == "cpu" else None)
        self.reduced = None
        if variable is not None:
            var = set(variable)
            moved = np.array([any(j in var for j, _ in hinges) for hinges in self.joints])  # carries one
            keep = moved.copy()
            for b in np.flatnonzero(moved):  # and their ancestors: a connected chain from the root
                p = self.parent[b]
                while p >= 0 and not keep[p]:
                    keep[p] = True
                    p = self.parent[p]
            if not keep.all():
                anchor = np.full(len(self.names), -1)  # nearest ancestor carrying a variable joint
                for b in np.flatnonzero(~keep):
                    p = self.parent[b]
                    while p >= 0 and not moved[p]:
                        p = self.parent[p]
                    anchor[b] = p
                static = np.flatnonzero(~keep)
                self.reduced = dict(
                    fk=self._subchain(kinematics, [n for n, k in zip(self.names, keep) if k], joint_names),
                    keep=np.flatnonzero(keep), anchored=static[anchor[static] >= 0],
                    anchor=anchor[static][anchor[static] >= 0], absolute=static[anchor[static] < 0],
                    fixed=np.array(sorted(set(self.cols.tolist()) - set(variable)), dtype=np.int64))
        #: per thread (pipeline workers share one solver geometry and solve different
        #: sequences): fixed joint values, anchored bodies' relative rot, pos, the others' rot, pos
        self._static: dict[int, tuple[np.ndarray, ...]] = {}

    def _subchain(self, kinematics: Kinematics, names: list[str],
                  joint_names: list[str]) -> tuple[object, torch.Tensor, torch.Tensor]:
        """The pk chain of `names`, its joint columns (robot order) and the names' chain frames."""
        chain = kinematics.subchain(names).to(device=self.device)
        cols = torch.tensor([joint_names.index(n) for n in chain.get_joint_parameter_names()],
                            device=self.device)
        return chain, cols, torch.tensor([chain.frame_to_idx[n] for n in names], device=self.device)

    def _chain_forward(self, fk: tuple, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        chain, cols, frames = fk
        with torch.no_grad():
            th = torch.as_tensor(q, dtype=torch.float64).to(self.device)[:, cols]
            t = chain.forward_kinematics_tensor(th)[frames].transpose(0, 1)  # (T,B,4,4)
            if self.base_shift is not None:  # exact: the identity rotation changes no bit
                t = t.numpy()
                return np.ascontiguousarray(t[..., :3, :3]), t[..., :3, 3] + self.base_shift
            rot = self.base_rot @ t[..., :3, :3]
            pos = t[..., :3, 3] @ self.base_rot.T + self.base_pos
        return rot.cpu().numpy(), pos.cpu().numpy()

    def forward_once(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whole chain, bypassing the static-body cache (which a batch of another shape
        would evict: the next `forward` would then take the other path, ~1e-16 apart)."""
        return self._chain_forward((self.chain, self.cols, self.frames), q)

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        red = self.reduced
        if red is None:
            return self._chain_forward((self.chain, self.cols, self.frames), q)
        fixed = np.asarray(q)[:, red["fixed"]]
        cache = self._static.get(threading.get_ident())
        if cache is None or cache[0].shape != fixed.shape or not np.array_equal(cache[0], fixed):
            rot, pos = self._chain_forward((self.chain, self.cols, self.frames), q)
            # static bodies relative to their anchor, and those with no anchor as they are
            a_rt = np.swapaxes(rot[:, red["anchor"]], -1, -2)
            rel_rot = a_rt @ rot[:, red["anchored"]]
            rel_pos = rotate(a_rt, pos[:, red["anchored"]] - pos[:, red["anchor"]])
            if len(self._static) >= 8:  # threads come and go: keep the latest few
                self._static.pop(next(iter(self._static)))
            self._static[threading.get_ident()] = (fixed.copy(), rel_rot, rel_pos,
                                                    rot[:, red["absolute"]], pos[:, red["absolute"]])
            return rot, pos
        _, rel_rot, rel_pos, abs_rot, abs_pos = cache
        rot = np.empty((len(q), len(self.names), 3, 3))
        pos = np.empty((len(q), len(self.names), 3))
        rot[:, red["keep"]], pos[:, red["keep"]] = self._chain_forward(red["fk"], q)
        a_rot = rot[:, red["anchor"]]
        rot[:, red["anchored"]] = a_rot @ rel_rot
        pos[:, red["anchored"]] = rotate(a_rot, rel_pos) + pos[:, red["anchor"]]
        rot[:, red["absolute"]], pos[:, red["absolute"]] = abs_rot, abs_pos
        return rot, pos
