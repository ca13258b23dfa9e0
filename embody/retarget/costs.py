"""IK tasks as weighted residuals with analytic Jacobians, for every frame at once (NumPy).

One residual vector per frame, r_t = [√w·(p − p*) for wrists and elbows, √w·log(R R*ᵀ) for the
wrists (and torso/head when weighted), √w·relu(margin − clearance) for near proxy pairs]. The
posture prior and the Δ²q smoothness are linear and handled by the solver. Jacobians are
geometric: for a hinge j with torso-frame axis z and pivot o, ∂p/∂q_j = z × (p − o) and the
rotation error moves by z (exact at zero error, which is where Gauss-Newton needs it), for
every point or frame downstream of j. One `KinematicTree` pass feeds everything.
"""

from __future__ import annotations

import numpy as np

from embody.config.ik import IKConfig
from embody.retarget.targets import Targets
from embody.robot import Robot
from embody.robot.proxies import robot_proxies

WRIST_ELBOW = ["left_wrist", "right_wrist", "left_elbow", "right_elbow"]


def rotation_log(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) (angle < π)."""
    v = 0.5 * np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    cos = np.clip((np.einsum("...ii->...", r) - 1.0) / 2.0, -1.0, 1.0)
    sin = np.linalg.norm(v, axis=-1)
    angle = np.arctan2(sin, cos)
    scale = np.where(sin > 1e-9, angle / np.maximum(sin, 1e-300), 1.0)
    return v * scale[..., None]


class Residuals:
    """r(q) (T,m) and J = ∂r/∂q_ik (T,m,n_ik) for a sequence's targets."""

    def __init__(self, robot: Robot, targets: Targets, cfg: IKConfig) -> None:
        self.robot, self.cfg = robot, cfg
        self.ik = np.flatnonzero(robot.ik_mask)
        self.rot_links = [n for n, w in (("spine3", cfg.w_torso_rot), ("head", cfg.w_head_rot))
                          if n in robot.spec.links and w > 0]
        links = WRIST_ELBOW + self.rot_links
        self.proxies = robot_proxies(robot) if cfg.w_collision > 0 and robot.spec.proxy_pairs else None
        proxy_bodies = self.proxies.bodies if self.proxies is not None else []
        refs = [robot.spec.links[n] for n in links]
        self.tree = robot.tree([r.body for r in refs] + proxy_bodies)
        self.link_body = [self.tree.index[r.body] for r in refs]
        self.link_offset = np.array([r.offset for r in refs])
        self.rot_cols = [0, 1] + list(range(4, 4 + len(self.rot_links)))
        self.sphere_body = ([self.tree.index[proxy_bodies[b]] for b in self.proxies.sphere_body]
                            if self.proxies is not None else [])
        self.mask = self.tree.moves(list(self.ik))  # (J, bodies)
        self.target_pos = np.concatenate([targets.wrist_pos, targets.elbow_pos], 1).astype(np.float64)
        rots = [np.asarray(targets.wrist_rot, dtype=np.float64)]
        rots += [np.asarray(targets.torso_rot if n == "spine3" else targets.head_rot, dtype=np.float64)[:, None]
                 for n in self.rot_links]
        self.target_rot = np.concatenate(rots, 1)  # (T,2+k,3,3)
        s = np.sqrt
        self.w_pos = np.array([s(cfg.w_wrist_pos)] * 2 + [s(cfg.w_elbow_pos)] * 2)
        self.w_rot = np.array([s(cfg.w_wrist_rot)] * 2 + [s(cfg.w_torso_rot if n == "spine3" else cfg.w_head_rot)
                                                          for n in self.rot_links])
        self.w_col = float(s(cfg.w_collision))

    def __call__(self, q: np.ndarray, jacobian: bool = False,
                 collision: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """q: full joint vectors (T, n_joints). `collision=False` leaves the proxy term out."""
        rot, pos = self.tree.forward(q)
        r_link = rot[:, self.link_body]
        p_link = pos[:, self.link_body] + np.einsum("tlab,lb->tla", r_link, self.link_offset)
        e_pos = (p_link[:, :4] - self.target_pos) * self.w_pos[:, None]
        r_rot = r_link[:, self.rot_cols]
        e_rot = rotation_log(r_rot @ np.swapaxes(self.target_rot, -1, -2)) * self.w_rot[:, None]
        res = [e_pos.reshape(len(q), -1), e_rot.reshape(len(q), -1)]
        near = None
        if self.proxies is not None and collision:
            sb = self.sphere_body
            centres = pos[:, sb] + np.einsum("tsab,sb->tsa", rot[:, sb], self.proxies.centres)
            pairs = self.proxies.pairs
            diff = centres[:, pairs[:, 0]] - centres[:, pairs[:, 1]]
            dist = np.linalg.norm(diff, axis=-1)
            clear = dist - self.proxies.radii[pairs[:, 0]] - self.proxies.radii[pairs[:, 1]]
            # Only pairs within the margin in some frame: the others contribute exactly zero.
            near = np.flatnonzero((clear < self.cfg.collision_margin).any(0))
            gap = np.maximum(self.cfg.collision_margin - clear[:, near], 0.0)
            res.append(self.w_col * gap)
        r = np.concatenate(res, 1)
        if not jacobian:
            return r, None
        z, o = self.tree.joint_frames(rot, pos, list(self.ik))  # (T,J,3) each

        def point_jac(p: np.ndarray, m: np.ndarray) -> np.ndarray:
            """(T,P,3) points moved by joints per mask (J,P) → (T,P,3,J)."""
            return np.cross(z[:, None], p[:, :, None] - o[:, None]).transpose(0, 1, 3, 2) * m.T[None, :, None]

        lm = self.mask[:, self.link_body]  # (J,L)
        jp = point_jac(p_link[:, :4], lm[:, :4]) * self.w_pos[None, :, None, None]
        jr = (z[:, None] * lm[:, self.rot_cols].T[None, :, :, None]).transpose(0, 1, 3, 2)
        jr = jr * self.w_rot[None, :, None, None]
        blocks = [jp.reshape(len(q), -1, len(self.ik)), jr.reshape(len(q), -1, len(self.ik))]
        if near is not None and len(near):
            i, k = pairs[near, 0], pairs[near, 1]
            ms = self.mask[:, sb]  # (J,N)
            ji = point_jac(centres[:, i], ms[:, i])
            jk = point_jac(centres[:, k], ms[:, k])
            u = diff[:, near] / np.maximum(dist[:, near], 1e-12)[..., None]
            dclear = np.einsum("tpa,tpaj->tpj", u, ji - jk)
            blocks.append(-self.w_col * (gap > 0)[..., None] * dclear)
        return r, np.concatenate(blocks, 1)
