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
        self.sphere_body = np.array([self.tree.index[proxy_bodies[b]] for b in self.proxies.sphere_body]
                                    if self.proxies is not None else [], dtype=np.int64)
        self.hull_body = np.array([self.tree.index[proxy_bodies[b]] for b in self.proxies.hull_body]
                                  if self.proxies is not None else [], dtype=np.int64)
        self.mask = self.tree.moves(list(self.ik))  # (J, bodies)
        if self.proxies is not None:
            self._group_hull_pairs()
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
        col = self._collision(rot, pos) if self.proxies is not None and collision else None
        if col is not None:
            res.append(col[0])
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
        if col is not None:
            blocks.append(col[1](z, o))
        return r, np.concatenate(blocks, 1)

    def _group_hull_pairs(self) -> None:
        """Bounding spheres of the sphere/hull pairs grouped by (sphere body, hull): a cheap first
        broad phase, so per-point plane tests run only where a whole body part is near a hull."""
        px = self.proxies
        key = px.sphere_body[px.hull_pairs[:, 0]] * (len(px.hull_body) + 1) + px.hull_pairs[:, 1]
        groups, inverse = np.unique(key, return_inverse=True)
        members = [np.flatnonzero(inverse == g) for g in range(len(groups))]
        width = max((len(m) for m in members), default=1)
        self.group_members = np.array([np.concatenate([m, np.full(width - len(m), -1)]) for m in members],
                                      dtype=np.int64).reshape(-1, width)
        first = px.hull_pairs[[m[0] for m in members]] if members else np.zeros((0, 2), dtype=np.int64)
        self.group_hull = first[:, 1]
        self.group_body = self.sphere_body[first[:, 0]] if members else np.zeros(0, dtype=np.int64)
        centre, radius = [], []
        for m in members:
            c = px.centres[px.hull_pairs[m, 0]]
            centre.append(c.mean(0))
            radius.append(float((np.linalg.norm(c - c.mean(0), axis=1) + px.radii[px.hull_pairs[m, 0]]).max()))
        self.group_centre = np.array(centre).reshape(-1, 3)
        self.group_radius = np.array(radius)

    def _collision(self, rot: np.ndarray, pos: np.ndarray):
        """Hinge residuals w·relu(margin − clearance) (T,P+Q) over the sphere/sphere and sphere/hull
        pairs within the margin somewhere, and a function of (axes, pivots) giving their Jacobian."""
        px, margin, w = self.proxies, self.cfg.collision_margin, self.w_col
        t = len(rot)
        sb, hb = self.sphere_body, self.hull_body
        centres = pos[:, sb] + np.einsum("tsab,sb->tsa", rot[:, sb], px.centres)
        i, k = px.pairs[:, 0], px.pairs[:, 1]
        diff = centres[:, i] - centres[:, k]
        dist = np.linalg.norm(diff, axis=-1)
        clear = dist - px.radii[i] - px.radii[k]
        near = np.flatnonzero((clear < margin).any(0))  # the other pairs contribute exactly zero
        i, k, diff, dist, clear = i[near], k[near], diff[:, near], dist[:, near], clear[:, near]
        # sphere/hull: broad phase per (body part, hull), then per point, then plane distances
        hb_g = hb[self.group_hull]
        gc = pos[:, self.group_body] + np.einsum("tgab,gb->tga", rot[:, self.group_body], self.group_centre)
        hc = pos[:, hb_g] + np.einsum("tgab,gb->tga", rot[:, hb_g], px.hull_centre[self.group_hull])
        gd = np.linalg.norm(gc - hc, axis=-1) - self.group_radius - px.hull_radius[self.group_hull]
        tg, gg = np.nonzero(gd < margin)
        members = self.group_members[gg]
        tc = np.repeat(tg, members.shape[1])
        qc = members.reshape(-1)
        tc, qc = tc[qc >= 0], qc[qc >= 0]
        si, hi = px.hull_pairs[:, 0], px.hull_pairs[:, 1]
        r_h, p_h = rot[tc, hb[hi[qc]]], pos[tc, hb[hi[qc]]]
        x = centres[tc, si[qc]]
        xl = np.einsum("cba,cb->ca", r_h, x - p_h)  # in the hull body's frame
        bound = np.linalg.norm(xl - px.hull_centre[hi[qc]], axis=-1) - px.hull_radius[hi[qc]] - px.radii[si[qc]]
        keep = bound < margin
        tc, qc, r_h, x, xl = tc[keep], qc[keep], r_h[keep], x[keep], xl[keep]
        planes = px.hull_planes[hi[qc]]
        sd = np.einsum("cfa,ca->cf", planes[..., :3], xl) + planes[..., 3]
        face = sd.argmax(1)
        value = sd[np.arange(len(qc)), face] - px.radii[si[qc]]
        hclear = np.full((t, len(si)), np.inf)
        hclear[tc, qc] = value
        hnear = np.flatnonzero((hclear < margin).any(0))
        gap = np.maximum(margin - clear, 0.0)
        hgap = np.maximum(margin - hclear[:, hnear], 0.0)
        sel = value < margin
        tc, qc, face, r_h, x = tc[sel], qc[sel], face[sel], r_h[sel], x[sel]
        normal = np.einsum("cab,cb->ca", r_h, px.hull_planes[hi[qc], face, :3])
        col = np.searchsorted(hnear, qc)

        def jacobian(z: np.ndarray, o: np.ndarray) -> np.ndarray:
            ms = self.mask[:, sb]  # (J,N)
            lever = lambda p: np.cross(z[:, None], p[:, :, None] - o[:, None])  # noqa: E731  (T,P,J,3)
            u = diff / np.maximum(dist, 1e-12)[..., None]
            dclear = (np.einsum("tpa,tpja->tpj", u, lever(centres[:, i])) * ms[:, i].T
                      - np.einsum("tpa,tpja->tpj", u, lever(centres[:, k])) * ms[:, k].T)
            jac = -w * (gap > 0)[..., None] * dclear
            hjac = np.zeros((t, len(hnear), z.shape[1]))
            arm = np.cross(z[tc], x[:, None] - o[tc])  # (C,J,3)
            moves = (ms[:, si[qc]] - self.mask[:, hb[hi[qc]]]).T  # (C,J)
            hjac[tc, col] = -w * np.einsum("ca,cja->cj", normal, arm) * moves
            return np.concatenate([jac, hjac], 1)

        return w * np.concatenate([gap, hgap], 1), jacobian
