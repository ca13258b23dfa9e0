"""Self-collision residuals from MuJoCo's exact geometry, for the IK's final polish phase.

The sphere/hull proxies need a 15 mm margin because they are sampled points and outer
polytopes: MuJoCo's meshes touch between the points at smaller margins. That margin is what
costs wrist accuracy wherever the targets bring a hand near the other hand or the body (the
all-frame error of benchmarks/ik_vs_mink.py sits there). Once the proxies have chosen the
basin, this term asks MuJoCo itself (the verdict of `embody.robot.contacts`): per frame,
`mj_collision` with a small geom margin on a copy of the model reports every counted pair
closer than `margin`, with its signed distance d, normal n (geom1 → geom2) and point; the
residual is √w·(margin − d) and its Jacobian −√w·nᵀ(J₂ − J₁) over the IK joints (the
separation rate used by `control.separate`). One row per geom pair and frame (its deepest
distance), packed per frame (the k-th pair of a frame in slot k), like the proxy rows.
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.robot import Robot
from embody.robot.contacts import collision_model


class ExactContacts:
    """Residual rows √w·relu(margin − d) over MuJoCo's contacts of every frame, with Jacobians."""

    def __init__(self, robot: Robot, margin: float, weight: float) -> None:
        self.robot, self.margin, self.w = robot, margin, float(np.sqrt(weight))
        # only the counted pairs the IK joints can move, each geom with `margin`
        self.model, self.relevant = collision_model(robot, margin, movable_only=True)
        self.data = mujoco.MjData(self.model)
        self.data.qpos[:] = self.model.qpos0
        jid = [self.model.joint(n).id for n in np.asarray(robot.joint_names)[robot.ik_mask]]
        self.cols = self.model.jnt_dofadr[jid]
        #: frames MuJoCo checks (None: all); the solver narrows it to frames near a contact
        self.frames: np.ndarray | None = None
        #: also these samples between frames: (frame t, fraction α) arrays, (1 − α)·q_t + α·q_t+1
        self.between: tuple[np.ndarray, np.ndarray] | None = None
        #: the smallest distance (m) MuJoCo reported in the last `rows` call (inf: none within
        #: the margin): ≥ 0 means no checked frame or sample penetrates
        self.deepest = np.inf
        #: (key of the poses checked, per pose the depth its contacts reached at the last call):
        #: the order a trial asks MuJoCo in (`_order`)
        self._weight: tuple[bytes, np.ndarray] = (b"", np.zeros(0))
        self._weight_key = b""
        self.jac1 = np.zeros((3, self.model.nv))
        self.jac2 = np.zeros((3, self.model.nv))

    def rows(self, q: np.ndarray, limit: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Residuals (T,K) and their Jacobian (T,K,n_ik) at full joint vectors q (T,n). `limit`:
        None as soon as the rows found so far have a sum of squares above it (the LM solver's
        trial that cannot win: MuJoCo is not asked about the frames and samples left). A call
        with a limit asks about the poses whose contacts were deepest at the last call on the
        same poses first (`_order`): rejected LM trials of the contact phase then stop after a
        few poses (benchmark seqs 0/1: 349 → 118 poses; MuJoCo takes ~210 µs a pose in contact,
        ~42 µs one without);
        the rows are the same bits in any order."""
        found: list[tuple] = []
        low: dict[tuple, float] = {}  # per row so far: its square, a lower bound of the final one
        frames = np.arange(len(q)) if self.frames is None else np.flatnonzero(self.frames)
        # the poses MuJoCo is asked about: each checked frame (j < F), then each sample between
        # frames t, t+1 (j = F + k); a sample's contact r, with Jacobian (1 − α)·J and α·J to
        # the two frames (the control-rate resample's (1 − α)·q_t + α·q_t+1), becomes rows
        # √(1 − α)·r and √α·r with Jacobians √(1 − α)·J and √α·J, one in each frame (the same
        # cost and gradient; the Gauss-Newton matrix drops the pair's cross term and its
        # diagonal blocks grow: steps only shorter)
        between = self.between if self.between is not None else (np.zeros(0, np.int64), np.zeros(0))
        n_pose = len(frames) + len(between[0])
        self._weight_key = frames.tobytes() + between[0].tobytes() + np.asarray(between[1]).tobytes()
        order: range | np.ndarray = range(n_pose)
        if limit is not None:  # a trial: the poses that weighed most last time first, so a trial
            # that cannot win passes `limit` after a few poses (the result does not depend on the
            # order: each pose files its rows under its own frame and tag)
            order = self._order(n_pose)
        weight = np.zeros(n_pose)
        for j in order:
            n = len(found)
            if j < len(frames):
                self._contacts(q[frames[j]], int(frames[j]), 1.0, 0, found)
            else:
                k = j - len(frames)
                t, a = int(between[0][k]), float(between[1][k])
                self._contacts((1.0 - a) * q[t] + a * q[t + 1], t, np.sqrt(1.0 - a), 1 + 2 * k, found)
                found += [(t + 1, r[1], np.sqrt(a), *r[3:5], 2 + 2 * k) for r in found[n:]]  # MuJoCo asked once
            if len(found) > n:
                weight[j] = sum(max(self.margin - f[1], 0.0) for f in found[n:])
                if limit is not None and self._over(found[n:], low, limit):
                    self._weight = (self._weight_key, np.maximum(self._weight[1], weight))
                    return None
        self._weight = (self._weight_key, weight)
        self.deepest = min((f[1] for f in found), default=np.inf)
        # one row per geom pair and frame: the model reports one point a pair (`single_contact`);
        # should a pair bring several, its row is its deepest distance with the mean separation
        # rate of the points at that depth (each pair weighs the same, however many points)
        pairs: dict[tuple[int, int, int, int], list] = {}
        for t, dist, scale, rate, (g1, g2), tag in found:
            key = (t, min(g1, g2), max(g1, g2), tag)
            best = pairs.get(key)
            if best is None or dist < best[0] - 1e-9:
                pairs[key] = [dist, [rate], scale]
            elif dist < best[0] + 1e-9:
                best[1].append(rate)
        frames = [key[0] for key in pairs]
        count = np.bincount(frames, minlength=len(q)) if pairs else np.zeros(len(q), np.int64)
        k = int(count.max()) if pairs else 0
        r = np.zeros((len(q), k))
        jac = np.zeros((len(q), k, len(self.cols)))
        #: the (geom, geom) pair of each row (T,K,2), −1 where a frame has fewer rows
        self.pairs = np.full((len(q), k, 2), -1, dtype=np.int64)
        slot = np.zeros(len(q), dtype=np.int64)
        for (t, g1, g2, _), (dist, rates, scale) in sorted(pairs.items()):
            r[t, slot[t]] = scale * self.w * (self.margin - dist)
            # (a pair's single point, the usual case, is its own mean: the same bits, no reduction)
            jac[t, slot[t]] = -scale * self.w * (rates[0] if len(rates) == 1 else np.mean(rates, axis=0))
            self.pairs[t, slot[t]] = (g1, g2)
            slot[t] += 1
        return r, jac

    def _order(self, n_pose: int) -> np.ndarray:
        """The poses (frames, then samples) by how deep their contacts were at the last call on
        the same poses, deepest first (stable: the others keep their order)."""
        key, weight = self._weight
        if key != self._weight_key or len(weight) != n_pose:
            self._weight = (self._weight_key, np.zeros(n_pose))
            return np.arange(n_pose)
        return np.argsort(-weight, kind="stable")

    def _over(self, new: list[tuple], low: dict[tuple, float], limit: float) -> bool:
        """Whether the rows of the contacts found so far (`low`, updated with `new`) already have a
        sum of squares above `limit`: a pair's row is its deepest point's, so each point's row
        value bounds it from below."""
        for t, dist, scale, _, (g1, g2), tag in new:
            key = (t, min(g1, g2), max(g1, g2), tag)
            low[key] = max(low.get(key, 0.0), (scale * self.w * max(self.margin - dist, 0.0)) ** 2)
        return sum(low.values()) > limit

    def _contacts(self, q: np.ndarray, t: int, scale: float, tag: int, found: list[tuple]) -> None:
        """Append (frame, distance, scaled residual factor and separation rate, geom pair, tag)
        for each relevant contact of MuJoCo at one full joint vector q, filed under frame t."""
        m, d = self.model, self.data
        d.qpos[self.robot.qpos_adr] = q  # the other coordinates stay at qpos0 (set once, in __init__)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        n = d.ncon
        if not n:
            return
        con = d.contact  # its arrays once (each access builds a view)
        geom, dist = con.geom[:n], con.dist[:n]
        hit = np.flatnonzero((dist < self.margin) & self.relevant[geom[:, 0], geom[:, 1]])
        if not len(hit):
            return
        mujoco.mj_comPos(m, d)
        pos, frame, body = con.pos, con.frame, m.geom_bodyid
        for i in hit:
            g1, g2 = int(geom[i, 0]), int(geom[i, 1])
            mujoco.mj_jac(m, d, self.jac1, None, pos[i], body[g1])
            mujoco.mj_jac(m, d, self.jac2, None, pos[i], body[g2])
            rate = frame[i, :3] @ (self.jac2 - self.jac1)[:, self.cols]
            found.append((t, float(dist[i]), scale, rate, (g1, g2), tag))
