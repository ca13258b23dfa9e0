"""IK tasks as weighted residuals with analytic Jacobians, frame by frame.

One residual vector per frame, r_t = [√w·(wrist pos), √w·(R_wrist − R*), √w·(elbow pos),
√w·(R_torso − R*), √w·(R_head − R*), √w·(q − q_rest), √w·relu(margin − clearance)]; the
Δ²q smoothness is linear and handled by the solver. Jacobians are geometric: for a hinge j with
world axis z and origin o, ∂p/∂q_j = z × (p − o) and ∂R/∂q_j = [z]ₓR, for every point or frame
downstream of j. Everything is evaluated from ONE batched pytorch-kinematics FK call.
"""

from __future__ import annotations

import numpy as np
import torch

from embody.config.ik import IKConfig
from embody.retarget.targets import Targets
from embody.robot import Robot
from embody.robot.proxies import robot_proxies

WRIST_ELBOW = ["left_wrist", "right_wrist", "left_elbow", "right_elbow"]


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)


class Residuals:
    """r(q) (T,m) and J = ∂r/∂q_ik (T,m,n_ik) for a sequence's targets."""

    def __init__(self, robot: Robot, targets: Targets, cfg: IKConfig, dtype: torch.dtype = torch.float64) -> None:
        self.robot, self.cfg, self.dtype = robot, cfg, dtype
        model = robot.model
        self.ik = np.flatnonzero(robot.ik_mask)
        self.rot_links = [n for n, w in (("spine3", cfg.w_torso_rot), ("head", cfg.w_head_rot))
                          if n in robot.spec.links and w > 0]
        self.links = WRIST_ELBOW + self.rot_links
        self.proxies = robot_proxies(robot) if cfg.w_collision > 0 and robot.spec.proxy_pairs else None
        joint_ids = [model.joint(robot.joint_names[j]).id for j in self.ik]
        joint_bodies = [model.body(int(model.jnt_bodyid[j])).name for j in joint_ids]
        link_bodies = [robot.spec.links[n].body for n in self.links]
        proxy_bodies = self.proxies.bodies if self.proxies is not None else []
        self.bodies = list(dict.fromkeys(link_bodies + proxy_bodies + joint_bodies))
        self.link_idx = [self.bodies.index(b) for b in link_bodies]
        self.proxy_idx = [self.bodies.index(b) for b in proxy_bodies]
        self.joint_idx = [self.bodies.index(b) for b in joint_bodies]
        self.axes = torch.as_tensor(model.jnt_axis[joint_ids], dtype=dtype)
        # mask[j, b] = 1 when joint j moves body b (j's body is b or one of its ancestors)
        parent = model.body_parentid
        ids = [model.body(b).id for b in self.bodies]
        mask = np.zeros((len(self.ik), len(self.bodies)))
        for k, jb in enumerate(model.jnt_bodyid[joint_ids]):
            for i, b in enumerate(ids):
                p = b
                while p > 0 and p != jb:
                    p = parent[p]
                mask[k, i] = float(p == jb)
        self.mask = torch.as_tensor(mask, dtype=dtype)
        as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)  # noqa: E731
        self.target_pos = torch.cat([as_t(targets.wrist_pos), as_t(targets.elbow_pos)], 1)  # (T,4,3)
        rots = [as_t(targets.wrist_rot)]
        rots += [as_t(targets.torso_rot if n == "spine3" else targets.head_rot)[:, None] for n in self.rot_links]
        self.target_rot = torch.cat(rots, 1)  # (T,2+k,3,3)
        s = np.sqrt
        self.w_pos = as_t([s(cfg.w_wrist_pos)] * 2 + [s(cfg.w_elbow_pos)] * 2)
        self.w_rot = as_t([s(cfg.w_wrist_rot)] * 2 + [s(cfg.w_torso_rot if n == "spine3" else cfg.w_head_rot)
                                                       for n in self.rot_links])
        self.rest = as_t(robot.rest[self.ik])

    def __call__(self, q: torch.Tensor, jacobian: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """q: full joint vectors (T, n_joints)."""
        cfg, robot = self.cfg, self.robot
        tf = robot.body_transforms(q, self.bodies)  # (T,B,4,4) torso frame
        pos, rot = robot.points_from(tf[:, self.link_idx], self.links)
        n_pos = 4
        res = [((pos[:, :n_pos] - self.target_pos) * self.w_pos[:, None]).flatten(1)]
        r_rot = rot[:, [0, 1] + list(range(4, 4 + len(self.rot_links)))]
        res.append(((r_rot - self.target_rot) * self.w_rot[:, None, None]).flatten(1))
        qi = q[:, torch.as_tensor(self.ik)]
        w_post = float(np.sqrt(cfg.w_posture))
        res.append(w_post * (qi - self.rest))
        if self.proxies is not None:
            centres = self.proxies.centres_from(tf[:, self.proxy_idx])
            # Only pairs within the margin in some frame: the others contribute exactly zero.
            clear = self.proxies.clearances(centres)
            near = torch.nonzero((cfg.collision_margin - clear > 0).any(0))[:, 0]
            clear = clear[:, near]
            res.append(float(np.sqrt(cfg.w_collision)) * torch.relu(cfg.collision_margin - clear))
        r = torch.cat(res, 1)
        if not jacobian:
            return r, None
        # geometric Jacobian pieces
        jt = tf[:, self.joint_idx]
        z = (jt[..., :3, :3] @ self.axes[..., None])[..., 0]  # (T,J,3)
        o = jt[..., :3, 3]
        link_mask = self.mask[:, self.link_idx]  # (J,L)

        def point_jac(p: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
            """(T,P,3) points with mask (J,P) → (T,P,3,J)."""
            d = p[:, None] - o[:, :, None]  # (T,J,P,3)
            return (torch.cross(z[:, :, None].expand_as(d), d, dim=-1) * m[None, :, :, None]).permute(0, 2, 3, 1)

        jp = point_jac(pos[:, :n_pos], link_mask[:, :n_pos]) * self.w_pos[None, :, None, None]
        rot_cols = [0, 1] + list(range(4, 4 + len(self.rot_links)))
        rm = link_mask[:, rot_cols]  # (J,K)
        jr = _skew(z)[:, :, None] @ r_rot[:, None]  # (T,J,K,3,3)
        jr = (jr * rm[None, :, :, None, None]).permute(0, 2, 3, 4, 1) * self.w_rot[None, :, None, None, None]
        blocks = [jp.flatten(1, 2), jr.flatten(1, 3),
                  w_post * torch.eye(len(self.ik), dtype=q.dtype, device=q.device).expand(len(q), -1, -1)]
        if self.proxies is not None:
            sm = self.mask[:, self.proxy_idx][:, torch.as_tensor(self.proxies.sphere_body)]  # (J,N)
            jc = point_jac(centres, sm)  # (T,N,3,J)
            pairs = torch.as_tensor(self.proxies.pairs, device=q.device)[near]
            i, k = pairs[:, 0], pairs[:, 1]
            diff = centres[:, i] - centres[:, k]
            u = diff / torch.linalg.norm(diff + 1e-12, dim=-1, keepdim=True)
            dclear = (u[..., None] * (jc[:, i] - jc[:, k])).sum(-2)  # (T,P,J)
            active = (cfg.collision_margin - clear > 0).to(q.dtype)[..., None]
            blocks.append(-float(np.sqrt(cfg.w_collision)) * active * dclear)
        return r, torch.cat(blocks, 1)
