"""Finger targets one hand can take: a handshape that would need two fingers of a hand through
each other, or through their palm, is met as closely as the hand allows.

Curl matching (`hands.retarget_hands`) maps each human finger on its own; the Dex3 thumb is
placed by its path position and the index/middle by their curls, so a pinch or a fist asks the
thumb's tip into the index finger (up to 23 mm on the collision hulls). Per frame and hand, the
finger joints q minimise

    Σ_j (q_j − q*_j)² + W · Σ_i relu(c − d_i(q))²

with q* the curl-matched values, d_i the signed distances MuJoCo reports between the hand's
counted geom pairs (the same pairs as the verdict, `robot.contacts`: fingers against fingers and
against the palm) and c = `CLEARANCE`: a differentiable clearance (d_i's rate over the finger
joints is n_iᵀ(J₂ − J₁)) solved by damped Gauss-Newton in the joint box. W is large, so the
fingers stop at the clearance, as a real hand stops where its fingers meet; frames whose
fingers are clear of each other keep their targets untouched.
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.robot import Robot
from embody.robot.contacts import counted_geom_pairs, single_contact
from embody.robot.exclusions import ancestors, hand_roots

#: Clearance (m) the fingers keep from each other and from the palm.
CLEARANCE = 0.002
#: Weight of a squared metre of missing clearance against a squared radian of finger change.
WEIGHT = 1e7
#: Gauss-Newton iterations per frame and hand at most.
ITERATIONS = 40
#: A frame's solve ends at an accepted step smaller than this (rad) on every joint.
STEP = 1e-3
#: Frames a robot's memo of solved frames keeps (per clearance) before it starts afresh.
MEMO_FRAMES = 100_000


class FingerClearance:
    """Per-frame projection of one robot's finger targets out of same-hand contact."""

    def __init__(self, robot: Robot, clearance: float = CLEARANCE) -> None:
        key = ("finger_clearance", float(clearance))
        if key not in robot.derived:
            robot.derived[key] = self._tables(robot, clearance)
        self.robot, self.clearance = robot, clearance
        models, self.counted = robot.derived[key]
        #: per hand: its collision model, one MjData and its finger joints
        self.hands = [(m, mujoco.MjData(m), cols) for m, cols in models]
        #: the robot's solved frames, by content: (hand, finger values) when clear as they are,
        #: (hand, finger values, the previous frame's) otherwise. A sequence's targets are built
        #: twice with the same finger targets (the retarget step's and the metrics step's IK-only
        #: baseline, whose targets differ elsewhere), and the second build finds them here.
        self.memo: dict[tuple, np.ndarray | None] = robot.derived.setdefault(("finger_clearance_memo", float(clearance)), {})
        m = robot.model
        self.jac1 = np.zeros((3, m.nv))
        self.jac2 = np.zeros((3, m.nv))
        self.dof = m.jnt_dofadr[[m.joint(n).id for n in robot.joint_names]]

    @staticmethod
    def _tables(robot: Robot, clearance: float) -> tuple[list[tuple[mujoco.MjModel, np.ndarray]], np.ndarray]:
        """Per hand, a model in which only that hand's counted pairs collide, with the clearance as
        their margin (MuJoCo reports the pairs closer than it: the only ones the cost sees, and a
        wider margin costs ~3x the narrow phase a call), and its finger joints (indices into the
        robot's joints); the counted table."""
        counted = counted_geom_pairs(robot)
        hands = []
        for root in hand_roots(robot.model, robot.spec):
            m = single_contact(robot.model.__copy__())  # the verdict's distances
            m.geom_contype[:] = 0
            m.geom_conaffinity[:] = 0
            inside = np.array([root in ancestors(m, int(b)) for b in m.geom_bodyid])
            used = inside & (counted & inside[None, :]).any(1)
            m.geom_contype[used] = 1
            m.geom_conaffinity[used] = 1
            m.geom_margin[used] = clearance
            side = next(s for s in robot.spec.hands
                        if any(root in ancestors(m, int(m.jnt_bodyid[m.joint(j).id]))
                               for j in robot.hand_joint_names(s)))
            hands.append((m, np.array([robot.joint_index(n) for n in robot.hand_joint_names(side)])))
        return hands, counted

    def _distances(self, hand: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances (K,) below the clearance of the counted pairs at joint values q (n,) in
        hand `hand`, and their indices into the hand's MjData contacts."""
        m, d, _ = self.hands[hand]
        d.qpos[self.robot.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        n = d.ncon
        if not n:
            return np.zeros(0), np.zeros(0, dtype=int)
        geom, dist = d.contact.geom[:n], d.contact.dist[:n]
        hit = np.flatnonzero((dist < self.clearance) & self.counted[geom[:, 0], geom[:, 1]])
        return dist[hit].copy(), hit

    def _rates(self, hand: int, hit: np.ndarray) -> np.ndarray:
        """Rates (K, H) of the distances of contacts `hit` (from the last `_distances` of hand
        `hand`) over its finger joints: n_iᵀ(J₂ − J₁)."""
        m, d, cols = self.hands[hand]
        rates = np.zeros((len(hit), len(cols)))
        if not len(hit):
            return rates
        mujoco.mj_comPos(m, d)
        dof = self.dof[cols]
        geom = d.contact.geom
        for k, i in enumerate(hit):
            b1, b2 = m.geom_bodyid[geom[i, 0]], m.geom_bodyid[geom[i, 1]]
            mujoco.mj_jac(m, d, self.jac1, None, d.contact.pos[i], b1)
            mujoco.mj_jac(m, d, self.jac2, None, d.contact.pos[i], b2)
            rates[k] = d.contact.frame[i, :3] @ (self.jac2 - self.jac1)[:, dof]
        return rates

    def _contacts(self, hand: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances (K,) below the clearance of the counted pairs at joint values q (n,) in
        hand `hand`, and their rates (K, H) over its finger joints."""
        dist, hit = self._distances(hand, q)
        return dist, self._rates(hand, hit)

    def _cost(self, hand: int, q: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The frame's cost at q, the missing clearance (S,) of the pairs short of it and their
        rates (S, H)."""
        cols = self.hands[hand][2]
        dist, hit = self._distances(hand, q)
        short = self.clearance - dist
        return float(((q[cols] - target) ** 2).sum() + WEIGHT * (short**2).sum()), short, self._rates(hand, hit)

    def solve_frame(self, hand: int, q: np.ndarray, start: np.ndarray | None = None) -> np.ndarray | None:
        """q (n,) with hand `hand`'s finger joints moved the least that clears its pairs, or None
        when they are clear as they are. `start`: finger values to start from instead of the
        target (a local minimum near them: the previous frame's side of a finger)."""
        cols = self.hands[hand][2]
        q = q.copy()
        target = q[cols].copy()
        lo, hi = self.robot.lower[cols], self.robot.upper[cols]
        cost, short, rates = self._cost(hand, q, target)
        if not len(short):
            return None
        if start is not None:
            q[cols] = np.clip(start, lo, hi)
            cost, short, rates = self._cost(hand, q, target)
        lam = 1e-3
        for _ in range(ITERATIONS):
            h = np.eye(len(cols)) + WEIGHT * rates.T @ rates
            g = (q[cols] - target) - WEIGHT * rates.T @ short
            for _ in range(8):
                trial = q.copy()
                trial[cols] = np.clip(q[cols] - np.linalg.solve(h + lam * np.eye(len(cols)), g), lo, hi)
                c, s, r = self._cost(hand, trial, target)
                if c < cost:
                    done = np.abs(trial[cols] - q[cols]).max() < STEP
                    q, cost, short, rates, lam = trial, c, s, r, max(lam / 3, 1e-6)
                    break
                lam *= 10
            else:
                break
            if done:
                break
        return q

    def _crosses(self, hand: int, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether hand `hand`'s fingers penetrate on the way from finger values a to b (samples
        at a quarter, half and three quarters)."""
        cols = self.hands[hand][2]
        x = q.copy()
        for f in (0.25, 0.5, 0.75):
            x[cols] = (1.0 - f) * a + f * b
            dist, _ = self._distances(hand, x)
            if (dist < 0).any():
                return True
        return False

    def apply(self, hand_q: np.ndarray, hand_joints: list[str], cleared: np.ndarray | None = None) -> np.ndarray:
        """Finger targets (T,H) in `hand_joints` order, each frame's hands out of contact.
        `cleared` (T,H): what a clearance returned for these frames before they were changed
        (the rate limit of `targets.build_targets` changes a few): a hand's frames equal to it
        keep their values, unless the frame before them changed (its side of a finger is
        checked again), so only the changed frames are solved again."""
        out = np.array(hand_q, dtype=np.float64, copy=True)
        if not len(out) or not self.hands:
            return out
        where = {self.robot.joint_index(n): c for c, n in enumerate(hand_joints)}
        q = np.tile(self.robot.tpose, (len(out), 1))
        for jn, c in zip(hand_joints, range(out.shape[1])):
            q[:, self.robot.joint_index(jn)] = out[:, c]
        for hand, (_, _, cols) in enumerate(self.hands):
            if not all(j in where for j in cols):
                continue  # a hand retargeted only in part keeps its targets
            slots = [where[j] for j in cols]
            frames = np.arange(len(out))
            if cleared is not None:
                changed = (out[:, slots] != np.asarray(cleared)[:, slots]).any(1)
                frames = np.flatnonzero(changed | np.r_[False, changed[:-1]])
            for t in frames:
                last = out[t - 1, slots] if t else None
                key = (hand, out[t, slots].tobytes())
                if key in self.memo:
                    continue  # clear as it is
                full = (*key, b"" if last is None else last.tobytes())
                if full in self.memo:
                    out[t, slots] = self.memo[full]
                    continue
                if len(self.memo) > MEMO_FRAMES:
                    self.memo.clear()
                qt = self.solve_frame(hand, q[t])
                if qt is not None and last is not None and self._crosses(hand, q[t], last, qt[cols]):
                    # the nearest clear pose lies on the other side of a finger than the last
                    # frame's: keep the side (a finger cannot pass through another between frames)
                    kept = self.solve_frame(hand, q[t], start=last)
                    if kept is not None and not self._crosses(hand, q[t], last, kept[cols]):
                        qt = kept
                if qt is None:
                    self.memo[key] = None
                else:
                    out[t, slots] = qt[cols]
                    self.memo[full] = out[t, slots]
        return out


def clear_fingers(robot: Robot, hand_q: np.ndarray, hand_joints: list[str],
                  clearance: float = CLEARANCE, cleared: np.ndarray | None = None) -> np.ndarray:
    """`hand_q` (T,H) with every frame's fingers clear of each other and of their palm by
    `clearance`, each changed the least (module docstring). `cleared`: the clearance's earlier
    result for frames of which only some have changed since (`FingerClearance.apply`)."""
    if not hand_joints:
        return np.array(hand_q, dtype=np.float64, copy=True)
    return FingerClearance(robot, clearance).apply(hand_q, hand_joints, cleared)
