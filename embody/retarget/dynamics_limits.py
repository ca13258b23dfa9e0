"""Torque and balance limits of the exported control-rate trajectory, owned by one solve.

A kinematically valid trajectory can still ask a wrist motor for three times its torque, or
accelerate the arms hard enough to push the standing robot's ZMP out of its feet. Both are set
by the accelerations of the exported samples, which the kinematic chain (resample, bridges,
contact pushes, velocity clamp) shapes last, so they are enforced on that array, with everything
the chain guaranteed kept in the same problem.

The torque is that of the curve the robot is commanded along: the natural cubic spline through
the samples, whose slopes and inverse dynamics the export sends as q̇ and feed-forward
(`physics.commands`, `dynamics.spline_derivatives`), so a limit held here holds in the replay.

What the solve acts on is what the validation and the physics replay refuse, by their own
definitions (`_Problem.failing_joints`): a sample whose exported feed-forward (rigid-body torque
plus the dry friction at the spline's slope) plus the PD's share while the joint's velocity
trails an accelerating reference by one command period (kd·|q̈|/rate, `_velocity_lag`: the
replay saturates there) passes a joint's effort limit itself; a cart-table ZMP
(`robot.dynamics.zmp`) closer than `zmp_margin` to the feet's edge; a velocity step past the
limit. A trajectory with none comes back unchanged (the same array): sign fidelity pays only
where the robot could not have executed the motion.

Where it must act, the excesses of retargeted sign motion are high-frequency (a 50 Hz zig-zag,
the kinks of a 30 → 50 Hz resample), so it starts by low-passing, around each failing sample
only, the whole upper body (arms, fingers and waist together: a limb low-passed alone moves
against the other limb, and the hands the contact repair kept 2 mm apart touch), the width
raised sample by sample until the sample passes, a width that makes MuJoCo find a new contact
taken back; then each changed region keeps the least share of its change that still passes
(`_local_start`). Where that leaves samples failing, the solve runs again low-passing only the
joint group at fault (the overloaded joint's arm, fingers or waist; for the ZMP the arms and the
waist), and the result with fewer failing samples is kept. Where that leaves a sample failing, a
sequential convex refinement follows on windows around it:

    min_x  ½ Σ_t (x_t − q_t)ᵀ W (x_t − q_t) + ½ w_s ‖Δ²(x − q)‖² + ½ w_h Σ hinge rows²

over the movable joints (arms, waist, fingers), its hinge rows zero inside the limits with a
margin (torque: |τ_rigid| + friction + kd·|q̈|/rate within `torque_fraction` of the limit,
linearised through M(x_t) and the spline's acceleration map, banded; the ZMP through the CoM
Jacobian; velocity; contacts on watched samples), a step kept only if the exact cost fell and
MuJoCo finds no sample it moved newly touching. A trajectory it cannot make feasible comes back
improved, never with a new contact, and the validation counts what is left (`torque_viol`),
which the export refuses.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
import scipy.sparse as sp
from scipy.linalg import solveh_banded
from threadpoolctl import threadpool_limits

from embody.config.ik import IKConfig
from embody.retarget.limits import EXPORT_GAP, clamp_velocity, velocity_violations
from embody.robot import Robot
from embody.robot.contacts import collision_model, near_contacts
from embody.robot.dynamics import (FRICTION_SPEED, GRAVITY, center_of_mass, derivatives, dof_adr,
                                   effort_limits, inverse_dynamics, leg_joints, spline_acceleration_matrix,
                                   spline_derivatives, stance_pose, standing_q, support_polygon)

log = logging.getLogger(__name__)

#: Cost of moving a joint class (larger = moved less): the arms carry the correction; the
#: fingers (the handshape carries meaning) and the waist (it moves the whole upper body) only
#: where needed.
WEIGHTS = {"arm": 1.0, "hand": 25.0, "waist": 25.0}
#: Outer (linearise, solve, accept) iterations at most.
ITERATIONS = 4
#: Weight of the hinge rows against the ½‖x − q‖²_W pull (rad²): a near-constraint.
W_HINGE = 1e5
#: Weight of the correction's second difference (rad²): a correction spread smoothly over its
#: window instead of a notch that moves the acceleration peak to its neighbours.
W_SMOOTH = 1000.0
#: Step halvings tried along one Gauss-Newton direction before the solve stops. The
#: linearisation holds only for small steps: the ZMP's CoM acceleration is the second difference
#: of a nonlinear CoM over one control period, so its second-order terms (δ²·link length / dt²)
#: grow fast.
BACKTRACK = 8
#: Largest change of any joint (rad) in one step.
MAX_STEP = 0.05
#: Hinge rows switch on this far inside their limit (torque: × the allowed share; ZMP: this
#: much (m) more than the margin), so that the solve converges from inside and stops there.
INNER = 0.97
ZMP_INNER = 0.003
INNER_VELOCITY = 0.99
#: Scale of a ZMP row (m) and of a contact row (m): the residual in these units is comparable to
#: a torque ratio.
ZMP_SCALE = 0.01
CONTACT_SCALE = 0.001
#: Contacts closer than this (m) are rows on a watched sample; the contact model reports up to
#: twice it.
CLEARANCE = 0.002
#: How far past CLEARANCE (m) a watched sample's contact row holds its pair. Why: the rows are
#: hinges, active only where the pair is already closer than their target, so a row at the
#: CLEARANCE itself never acts on a pair that is clear now but that the step closes (synth seq 16:
#: one sample touched on every trial step of the Gauss-Newton and the solve stalled there).
WATCH_BUFFER = 0.001
#: How far (s) on each side of a violating sample the trajectory may change.
REACH_S = 0.5


@dataclass(frozen=True)
class DynamicsLimits:
    """What the exported array must honour: `torque_fraction` of each effort limit and `zmp_margin`
    (m) inside the standing robot's feet."""

    torque_fraction: float = 0.9
    zmp_margin: float = 0.02

    @classmethod
    def from_config(cls, cfg: Any) -> "DynamicsLimits | None":
        """From an `IKConfig`; None when `dynamics_limits` is off."""
        if not cfg.dynamics_limits:
            return None
        return cls(float(cfg.torque_limit_fraction), float(cfg.zmp_margin))


#: The `ik` section's defaults (`torque_limit_fraction`, `zmp_margin`).
DEFAULT_LIMITS = DynamicsLimits(IKConfig().torque_limit_fraction, IKConfig().zmp_margin)


def _second_difference(t: int, dt: float) -> sp.csr_matrix:
    """(T,T) the acceleration operator of `dynamics.derivatives`: central second differences / dt²,
    the end rows copying their neighbours'."""
    if t < 3:
        return sp.csr_matrix((t, t))
    rows = np.repeat(np.arange(1, t - 1), 3)
    cols = (np.arange(1, t - 1)[:, None] + np.array([-1, 0, 1])).ravel()
    vals = np.tile([1.0, -2.0, 1.0], t - 2)
    rows = np.r_[rows, 0, 0, 0, t - 1, t - 1, t - 1]
    cols = np.r_[cols, 0, 1, 2, t - 3, t - 2, t - 1]
    vals = np.r_[vals, 1.0, -2.0, 1.0, 1.0, -2.0, 1.0]
    return sp.csr_matrix((vals / dt**2, (rows, cols)), shape=(t, t))


def _velocity_lag(robot: Robot) -> np.ndarray:
    """Per joint (n,) the torque per unit acceleration (N·m·s²/rad) the motor's damping adds
    while its velocity lags one control period behind an accelerating reference: kd / rate.
    Why: a command is held for a period, so at the next one the joint's velocity trails the
    reference's by q̈ / rate, and the PD asks kd · q̈ / rate on top of the feed-forward (a G1
    wrist at 200 rad/s²: 1.2 N·m of its 5). Zero where the robot has no `actuation`."""
    try:
        from embody.physics.actuation import actuation
        act = actuation(robot)
    except Exception:  # noqa: BLE001 (a robot without gains: no lag to allow for)
        return np.zeros(robot.n_joints)
    return act.kd / act.rate_hz


#: Samples on each side of the diagonal kept of the spline acceleration's map in the linearised
#: torque rows (the dropped entries are below 0.268^(BAND+1)·√3 of the diagonal's).
BAND = 3


def _spline_acceleration(t: int, dt: float) -> sp.csr_matrix:
    """(T,T) the natural cubic spline's knot accelerations from the samples
    (`dynamics.spline_acceleration_matrix`), truncated to ±BAND samples: a banded Jacobian."""
    full = spline_acceleration_matrix(t, dt)
    i, j = np.indices(full.shape)
    return sp.csr_matrix(np.where(np.abs(i - j) <= BAND, full, 0.0))


def _joint_groups(robot: Robot, movable: np.ndarray) -> tuple[np.ndarray, list[list[int]], np.ndarray]:
    """The movable joints in groups that the solve's low-pass moves together: per limb hanging
    from the torso its arm joints and its fingers, and the waist (joints at or below the torso
    body). Returns the group (nm,) of each movable joint, per group the groups added when its
    own low-pass is at its widest (fingers: their arm, whose acceleration loads them too; the
    waist: the arms), and
    (G,) the groups that carry the upper body's CoM (arms and waist, not fingers)."""
    m = robot.model
    torso = m.body(robot.spec.torso_body).id
    hands = {j for side in robot.spec.hands for j in robot.hand_joint_names(side)}
    keys: list[tuple[str, int]] = []
    group = np.empty(len(movable), dtype=np.int64)
    for c, i in enumerate(movable):
        name = robot.joint_names[i]
        body = int(m.jnt_bodyid[m.joint(name).id])
        limb = -1
        while body > 0 and body != torso:
            limb, body = body, int(m.body_parentid[body])
        key = ("waist", -1) if body != torso or limb < 0 else ("hand" if name in hands else "arm", limb)
        if key not in keys:
            keys.append(key)
        group[c] = keys.index(key)
    arms = [k for k, (kind, _) in enumerate(keys) if kind == "arm"]
    escalate = [[keys.index(("arm", limb))] if kind == "hand" and ("arm", limb) in keys else
                arms if kind == "waist" else [] for kind, limb in keys]
    upper = np.array([kind != "hand" for kind, _ in keys])
    return group, escalate, upper


class _Rows:
    """Triplets of the linearised hinge rows (sparse), their residuals."""

    def __init__(self) -> None:
        self.r: list[float] = []
        self.i: list[np.ndarray] = []
        self.j: list[np.ndarray] = []
        self.v: list[np.ndarray] = []

    def add(self, residual: float, cols: np.ndarray, vals: np.ndarray) -> None:
        self.i.append(np.full(len(cols), len(self.r)))
        self.j.append(cols)
        self.v.append(vals)
        self.r.append(residual)

    def matrix(self, n: int) -> tuple[sp.csr_matrix, np.ndarray]:
        if not self.r:
            return sp.csr_matrix((0, n)), np.zeros(0)
        a = sp.csr_matrix((np.concatenate(self.v), (np.concatenate(self.i), np.concatenate(self.j))),
                          shape=(len(self.r), n))
        return a, np.array(self.r)


class _Problem:
    """The robot's dynamics and contacts for one control-rate trajectory."""

    def __init__(self, robot: Robot, q: np.ndarray, rate: float, limits: DynamicsLimits,
                 box_margin: float, velocity_margin: float, whole: bool = True) -> None:
        self.robot, self.q0, self.dt = robot, np.array(q, dtype=np.float64), 1.0 / rate
        self.limits = limits
        hands = {j for side in robot.spec.hands for j in robot.hand_joint_names(side)}
        waist = set(robot.waist_joint_names)
        names = robot.joint_names
        self.movable = np.array([i for i, n in enumerate(names) if robot.ik_mask[i] or n in hands])
        self.weight = np.array([WEIGHTS["waist"] if names[i] in waist else
                                WEIGHTS["hand"] if names[i] in hands else WEIGHTS["arm"] for i in self.movable])
        self.dof = dof_adr(robot)
        self.effort = effort_limits(robot)
        self.limited = np.isfinite(self.effort)
        # the dry friction, whatever its sign at a reversal: |rigid-body torque| + friction is held
        self.friction = robot.model.dof_frictionloss[self.dof]
        self.lag = _velocity_lag(robot)
        self.lower = robot.lower + box_margin
        self.upper = robot.upper - box_margin
        self.vstep = robot.velocity_limits * (1.0 - velocity_margin) * self.dt
        self.d2 = _second_difference(len(q), self.dt)  # the ZMP's CoM acceleration
        self.acc = _spline_acceleration(len(q), self.dt)  # the torque's joint acceleration
        # the velocity hinge starts INNER_VELOCITY inside the limit, or at the input's own speed
        # where that is closer (the clamp leaves runs at the limit, and those cost nothing as given)
        self.vstart = np.maximum(INNER_VELOCITY * self.vstep, np.abs(np.diff(self.q0, axis=0)))
        self.dyn = mujoco.MjData(robot.model)  # M(q) with the base fixed: the joint block of qM
        self.fullm = np.zeros((robot.model.nv, robot.model.nv))
        self.jac = np.zeros((3, robot.model.nv))
        self.root = robot.model.body(robot.spec.root_body).id
        self.legs = leg_joints(robot)
        self.stance = stance_pose(robot)
        stand = robot.tpose.copy()
        stand[self.legs] = self.stance[self.legs]
        self.polygon, self.floor = support_polygon(robot, stand)
        self.cmodel, self.counted = collision_model(robot, margin=2 * CLEARANCE)
        self.cdata = mujoco.MjData(self.cmodel)
        self.jac2 = np.zeros((3, self.cmodel.nv))
        self.watch: set[int] = set()
        self.group, self.escalate, self.upper_body = _joint_groups(robot, self.movable)
        self.whole = whole  # `culprits`: every group low-passed together

    # --- exact evaluation --------------------------------------------------------------------

    def evaluate(self, x: np.ndarray, near: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Torques (T,n), ZMP (T,2), the polygon's edge margins (T,E), and the hinge excesses.
        `near`: the evaluation of a trajectory that differs from x on some samples only; the
        torques and CoM of the samples whose own values and differences are the same are kept."""
        qd, qdd = spline_derivatives(x, self.dt)
        if near is None:
            tau = inverse_dynamics(self.robot, x, self.dt, qd, qdd, friction=False)
            com = center_of_mass(self.robot, standing_q(self.robot, x))
        else:
            moved = np.any(x != near["x"], axis=1)
            # the spline couples every sample, its reach decaying 0.27× per sample: the samples
            # whose derivatives changed past rounding are recomputed, the rest kept
            redo = moved | (np.abs(qd - near["qd"]).max(1) > 1e-9) | (np.abs(qdd - near["qdd"]).max(1) > 1e-7)
            tau, com = near["tau"].copy(), near["com"].copy()
            if redo.any():
                tau[redo] = inverse_dynamics(self.robot, x[redo], self.dt, qd[redo], qdd[redo], friction=False)
            if moved.any():
                com[moved] = center_of_mass(self.robot, standing_q(self.robot, x[moved]))
        # `dynamics.zmp`'s cart-table ZMP, its support polygon computed once
        _, cdd = derivatives(com, self.dt)
        lever = (com[:, 2] - self.floor) / (cdd[:, 2] + GRAVITY)
        point = com[:, :2] - lever[:, None] * cdd[:, :2]
        polygon = self.polygon
        a, b = polygon, np.roll(polygon, -1, axis=0)
        e = b - a
        inward = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1)[:, None]
        edge = ((point[:, None, :] - a[None]) * inward[None]).sum(-1)  # (T,E)
        bound = self.limits.torque_fraction * self.effort
        over_tau = np.where(self.limited, (np.abs(tau) + self.friction + self.lag * np.abs(qdd)
                                            - INNER * bound) / self.effort, 0.0)
        target = self.limits.zmp_margin + ZMP_INNER
        over_zmp = (target - edge) / ZMP_SCALE
        step = np.abs(np.diff(x, axis=0))
        over_vel = (step - self.vstart) / self.vstep
        return {"x": x, "qd": qd, "qdd": qdd, "com": com, "lever": lever, "tau": tau, "point": point, "inward": inward, "corner": a, "edge": edge,
                "over_tau": over_tau, "over_zmp": over_zmp, "over_vel": over_vel, "target": target}

    def failing_joints(self, ev: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the validation and the physics replay refuse, per sample: (T,n) joints whose
        exported feed-forward (rigid-body torque plus the dry friction at the spline's slope,
        `dynamics.inverse_dynamics`) plus the PD's lag share (`_velocity_lag`) passes the effort
        limit itself, (T,) ZMP closer than `zmp_margin` to the feet's edge, (T,) a velocity step
        past the limit."""
        ff = ev["tau"] + self.friction * np.tanh(ev["qd"] / FRICTION_SPEED)
        tau = (np.abs(ff) + self.lag * np.abs(ev["qdd"]) > self.effort * (1.0 + 1e-9)) & self.limited
        zmp_ = (ev["edge"] < self.limits.zmp_margin).any(1)
        vel = np.zeros(len(tau), dtype=bool)
        v = (np.abs(np.diff(ev["x"], axis=0)) > self.vstep * (1.0 + 1e-9)).any(1)
        vel[1:] |= v
        vel[:-1] |= v
        return tau, zmp_, vel

    def failing(self, ev: dict[str, np.ndarray]) -> np.ndarray:
        """(T,) bool: samples the validation or the replay refuses (`failing_joints`)."""
        tau, zmp_, vel = self.failing_joints(ev)
        return tau.any(1) | zmp_ | vel

    def culprits(self, ev: dict[str, np.ndarray]) -> np.ndarray:
        """(T,G) bool: per failing sample the joint groups whose motion is low-passed first: with
        `whole`, every group (arms, fingers and waist together); else a joint over its torque,
        its own group (the arm of a limb, its fingers, the waist), a ZMP short of its margin,
        every arm and the waist (the upper body's CoM)."""
        tau, zmp_, _ = self.failing_joints(ev)
        n_groups = len(self.escalate)
        out = np.zeros((len(tau), n_groups), dtype=bool)
        gj = np.full(self.robot.n_joints, -1)
        gj[self.movable] = self.group
        for g in range(n_groups):
            out[:, g] = tau[:, gj == g].any(1)
        out[zmp_] |= self.upper_body
        if self.whole:
            out[out.any(1)] = True
        return out

    def cost(self, x: np.ndarray, ev: dict[str, np.ndarray]) -> float:
        d = x - self.q0
        hinge = sum(float((np.maximum(ev[k], 0.0) ** 2).sum()) for k in ("over_tau", "over_zmp", "over_vel"))
        s = d[2:] - 2.0 * d[1:-1] + d[:-2]
        return 0.5 * (W_HINGE * hinge + float((self.weight * d[:, self.movable] ** 2).sum())
                      + W_SMOOTH * float((s[:, self.movable] ** 2).sum()))

    def watch_near(self, x: np.ndarray, free: np.ndarray) -> None:
        """Watch (contact rows) the free samples with a counted contact closer than 2 × CLEARANCE."""
        m, d = self.cmodel, self.cdata
        for t in np.flatnonzero(free):
            if t in self.watch:
                continue
            d.qpos[:] = m.qpos0
            d.qpos[self.robot.qpos_adr] = x[t]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            geom = d.contact.geom[: d.ncon]
            if d.ncon and self.counted[geom[:, 0], geom[:, 1]].any():
                self.watch.add(int(t))

    # --- linearisation --------------------------------------------------------------------------

    def _mass(self, qt: np.ndarray) -> np.ndarray:
        d, m = self.dyn, self.robot.model
        d.qpos[:] = self.robot.qpos(qt)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_crb(m, d)
        mujoco.mj_fullM(m, d, self.fullm)
        return self.fullm[np.ix_(self.dof, self.dof[self.movable])]

    def _com_jacobian(self, qt: np.ndarray) -> np.ndarray:
        d, m = self.dyn, self.robot.model
        q = qt.copy()
        q[self.legs] = self.stance[self.legs]
        d.qpos[:] = self.robot.qpos(q)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_jacSubtreeCom(m, d, self.jac, self.root)
        return self.jac[:, self.dof[self.movable]].copy()

    def contact_rows(self, qt: np.ndarray) -> list[tuple[float, np.ndarray]]:
        """(distance, a) of each counted contact closer than twice CLEARANCE at sample qt: the
        distance changes by a·δ_t (movable joints)."""
        m, d = self.cmodel, self.cdata
        d.qpos[:] = m.qpos0
        d.qpos[self.robot.qpos_adr] = qt
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_collision(m, d)
        out = []
        cols = self.dof[self.movable]
        for c in d.contact[: d.ncon]:
            if not self.counted[c.geom[0], c.geom[1]] or c.dist >= 2 * CLEARANCE:
                continue
            b1, b2 = m.geom_bodyid[c.geom[0]], m.geom_bodyid[c.geom[1]]
            mujoco.mj_jac(m, d, self.jac2, None, c.pos, b1)
            jac1 = self.jac2[:, cols].copy()
            mujoco.mj_jac(m, d, self.jac2, None, c.pos, b2)
            out.append((float(c.dist), c.frame[:3] @ (self.jac2[:, cols] - jac1)))
        return out

    def rows(self, x: np.ndarray, ev: dict[str, np.ndarray], free: np.ndarray) -> _Rows:
        """The active hinge rows at x, over the free samples' movable joints (column
        index·n_movable + k for the index-th free sample)."""
        nm = len(self.movable)
        col = np.full(len(x), -1)
        col[free] = np.arange(int(free.sum()))
        out = _Rows()
        d2 = self.d2

        def place(s: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Columns and values of per-sample row pieces vals (len(s), nm) at samples s."""
            keep = col[s] >= 0
            c = (col[s[keep]][:, None] * nm + np.arange(nm)[None]).ravel()
            return c, vals[keep].ravel()

        acc = self.acc
        tt, jj = np.nonzero(ev["over_tau"] > 0)
        for t in np.unique(tt):
            s = acc.indices[acc.indptr[t]: acc.indptr[t + 1]]
            w = acc.data[acc.indptr[t]: acc.indptr[t + 1]]
            if not (col[s] >= 0).any():
                continue
            mass = self._mass(x[t])
            for j in jj[tt == t]:
                sign = np.sign(ev["tau"][t, j]) / self.effort[j]
                piece = w[:, None] * mass[j][None] * sign
                k = np.flatnonzero(self.movable == j)
                if len(k):  # the damping's lag grows with the joint's own acceleration
                    piece[:, k[0]] += w * self.lag[j] * np.sign(ev["qdd"][t, j]) / self.effort[j]
                c, v = place(s, piece)
                out.add(float(ev["over_tau"][t, j]), c, v)
        tz, ez = np.nonzero(ev["over_zmp"] > 0)
        if len(tz):
            need = np.unique(np.concatenate([d2.indices[d2.indptr[t]: d2.indptr[t + 1]] for t in tz] + [tz]))
            jac = {int(s): self._com_jacobian(x[s]) for s in need}
            for t in np.unique(tz):
                s = d2.indices[d2.indptr[t]: d2.indptr[t + 1]]
                w = d2.data[d2.indptr[t]: d2.indptr[t + 1]]
                k = ev["lever"][t]
                for e in ez[tz == t]:
                    n = ev["inward"][e]
                    pieces = np.stack([k * wi * (n @ jac[int(si)][:2]) for si, wi in zip(s, w)])
                    pieces[s == t] -= n @ jac[int(t)][:2]
                    c, v = place(s, pieces / ZMP_SCALE)
                    out.add(float(ev["over_zmp"][t, e]), c, v)
        tv, jv = np.nonzero(ev["over_vel"] > 0)
        for t, j in zip(tv, jv):
            k = np.flatnonzero(self.movable == j)
            if not len(k):
                continue
            sign = np.sign(x[t + 1, j] - x[t, j]) / self.vstep[j]
            cols, vals = [], []
            for s, w in ((t + 1, sign), (t, -sign)):
                if col[s] >= 0:
                    cols.append(col[s] * nm + k[0])
                    vals.append(w)
            if cols:
                out.add(float(ev["over_vel"][t, j]), np.array(cols), np.array(vals))
        for t in sorted(self.watch):
            if col[t] < 0:
                continue
            for dist, a in self.contact_rows(x[t]):
                if dist < CLEARANCE + WATCH_BUFFER:
                    c, v = place(np.array([t]), (-a / CONTACT_SCALE)[None])
                    out.add((CLEARANCE + WATCH_BUFFER - dist) / CONTACT_SCALE, c, v)
        return out


def _solve_banded(h: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """Solve h x = b for a symmetric positive definite sparse h whose unknowns couple only near
    the diagonal (sample-major order: rows reach two samples): LAPACK's banded Cholesky."""
    h = sp.tril(h, format="coo")
    width = int((h.row - h.col).max(initial=0)) + 1
    ab = np.zeros((width, h.shape[0]))
    np.add.at(ab, (h.row - h.col, h.col), h.data)
    return solveh_banded(ab, b, lower=True, check_finite=False)


def _dilate(mask: np.ndarray, pad: int) -> np.ndarray:
    out = mask.copy()
    for k in range(1, pad + 1):
        out[k:] |= mask[:-k]
        out[:-k] |= mask[k:]
    return out


def enforce_dynamics(robot: Robot, q: np.ndarray, rate: float, limits: DynamicsLimits, *,
                     box_margin: float = 0.0, velocity_margin: float = 0.0,
                     touching: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """q (T,n) at `rate` Hz moved (least weighted, smooth change) until the inverse-dynamics torque
    of every sample is within `limits.torque_fraction` of its effort limit and the standing
    robot's ZMP `limits.zmp_margin` inside its feet, inside the joint box (shrunk by
    `box_margin`) and the velocity limits (× (1 − velocity_margin)), with no sample it moved
    touching in MuJoCo; and whether every limit holds. An input already inside comes back as is.
    `touching` (T,) bool: samples of q MuJoCo finds touching (left to the caller's verdict)."""
    q = np.array(q, dtype=np.float64)
    if len(q) < 3:
        return q, True
    with threadpool_limits(limits=1, user_api="blas"):  # banded solves of ~100-wide bands
        return _enforce(robot, q, rate, limits, box_margin, velocity_margin, touching)


#: Widths (Gaussian σ, samples) of the low-pass the solve starts from, raised in turn around the
#: samples still failing. Why: the torque and ZMP excesses of retargeted sign motion are
#: high-frequency (a 50 Hz zig-zag, the kinks of a 30 → 50 Hz resample), which a low-pass of a
#: few samples removes where the Gauss-Newton on the active hinge rows alone, starting from the
#: input, fixes the active rows by pushing their neighbours over (≥ 30 iterations).
SIGMAS = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
#: Shares of a region's low-pass change tried, smallest first, once the region passes: the
#: least of it that still passes is kept (the change is paid in sign fidelity).
SHARES = (0.25, 0.5, 0.75)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each run of True in mask."""
    edge = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)))


def _blend(prob: "_Problem", q: np.ndarray, passes: list[np.ndarray], level: np.ndarray) -> np.ndarray:
    """q with each joint group's motion low-passed to its per-sample level (level k: the k-th
    width of SIGMAS; 0: q), each level's region ramped in over its own width (a smooth blend of
    low-passes of q: inside the joint box, no faster than q but for the ramps)."""
    from scipy.ndimage import gaussian_filter1d

    mov = prob.movable
    moved = q[:, mov].copy()
    for g in range(level.shape[1]):
        cols = prob.group == g
        for k in range(1, int(level[:, g].max(initial=0)) + 1):
            share = gaussian_filter1d((level[:, g] >= k).astype(np.float64), SIGMAS[k - 1], mode="nearest")
            share = np.clip(2.0 * share, 0.0, 1.0)  # full inside the level's region, ramp outside
            moved[:, cols] += share[:, None] * (passes[k][:, cols] - passes[k - 1][:, cols])
    out = q.copy()
    out[:, mov] = np.clip(moved, prob.lower[mov], prob.upper[mov])
    return out


def _touching(robot: Robot, x: np.ndarray, rows: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(len(rows),) bool: samples `rows` of x MuJoCo finds touching that q had clear (`prior`)."""
    if not len(rows):
        return np.zeros(0, dtype=bool)
    return (near_contacts(robot, x[rows], EXPORT_GAP) > 0) & ~prior[rows]


#: Half width (s) of the hat a contact push in the start is spread over.
PUSH_HAT_S = 0.2
#: Width (Gaussian σ, samples) of the low-pass applied to a contact push.
PUSH_SIGMA = 2.0
#: Trust radii (deg) and passes per radius of a push: the repair's small radii only (its full
#: ladder, up to an unbounded push, cost over 100 CPU-s on synth seq 17 under load).
PUSH_TRUST_DEG = (5.0, 10.0)
PUSH_PASSES = 6


def _push_clear(prob: "_Problem", trial: np.ndarray, touch: np.ndarray, prior: np.ndarray, rate: float,
                box_margin: float, velocity_margin: float) -> np.ndarray | None:
    """trial with its `touch` samples pushed clear by the contact repair (`control.separate_checked`
    on a wide hat, the push low-passed as the motion is: its hat's kinks are accelerations), or
    None when no small push clears them."""
    from scipy.ndimage import gaussian_filter1d

    from embody.retarget.control import separate_checked
    mov = prob.movable
    kw = {"box_margin": box_margin, "velocity_margin": velocity_margin, "touching": touch, "gap": EXPORT_GAP,
          "enforce_velocity": False, "blend_s": PUSH_HAT_S, "passes": PUSH_PASSES}
    pushed = trial
    for _push in range(3):
        step, clear = separate_checked(prob.robot, pushed, rate, trust_deg=PUSH_TRUST_DEG, **kw)
        if not clear:
            return None
        pushed = pushed + gaussian_filter1d(step - pushed, PUSH_SIGMA, axis=0, mode="nearest")
        pushed[:, mov] = np.clip(pushed[:, mov], prob.lower[mov], prob.upper[mov])
        pushed = clamp_velocity(pushed, prob.robot.velocity_limits * (1.0 - velocity_margin), rate)
        moved = np.flatnonzero(np.abs(pushed - trial).max(1) > 0)
        kw["touching"] = np.zeros(len(trial), dtype=bool)
        kw["touching"][moved] = _touching(prob.robot, pushed, moved, prior)
        if not kw["touching"].any():
            return pushed
    return None


def _local_start(prob: "_Problem", q: np.ndarray, ev: dict[str, np.ndarray], prior: np.ndarray,
                 rate: float, box_margin: float, velocity_margin: float
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The solve's start: around each failing sample, only the joint groups at fault
    (`_Problem.culprits`: the overloaded joint's own group; for the ZMP the arms and the waist)
    low-passed, the width raised sample by sample (`SIGMAS`) until the sample passes; a group at
    its widest that still fails brings in the groups it escalates to (fingers: their arm). A
    sample the low-pass makes touch (MuJoCo; q had it clear: `prior`) gets a small push
    (`_push_clear`, kept under later widths); where none clears it, the widths of the groups
    that made it go back one step, capped there (the Gauss-Newton's contact rows take over). Then each changed region keeps the smallest share of its change that
    still passes (`SHARES`). MuJoCo checks only the samples each step changed."""
    from scipy.ndimage import gaussian_filter1d

    mov = prob.movable
    passes = [q[:, mov]] + [gaussian_filter1d(q[:, mov], s, axis=0, mode="nearest") for s in SIGMAS]
    n_groups = len(prob.escalate)
    level = np.zeros((len(q), n_groups), dtype=np.int64)
    cap = np.full((len(q), n_groups), len(SIGMAS), dtype=np.int64)
    x = q
    push = np.zeros_like(q)  # the contact pushes so far, kept on top of every later blend
    hopeless = np.zeros(len(q), dtype=bool)  # samples no push cleared
    for _ in range(3 * len(SIGMAS)):
        want = prob.culprits(ev)
        maxed = want & (level >= cap)
        for g in range(n_groups):
            for h in prob.escalate[g]:
                want[:, h] |= maxed[:, g]
        bad = want & (level < cap)
        if not bad.any():
            break
        for g in range(n_groups):
            for k in range(len(SIGMAS), 0, -1):
                at = bad[:, g] & (level[:, g] == k - 1)
                if at.any():
                    grow = _dilate(at, int(np.ceil(3.0 * SIGMAS[k - 1])))
                    level[grow, g] = np.minimum(np.maximum(level[grow, g], k), cap[grow, g])
        trial = np.clip(_blend(prob, q, passes, level) + push, prob.lower, prob.upper)
        changed = np.flatnonzero(np.abs(trial - x).max(1) > 0)
        touch = np.zeros(len(q), dtype=bool)
        touch[changed] = _touching(prob.robot, trial, changed, prior)
        log.debug("start round: %d bad, %d changed, %d touching", int(bad.any(1).sum()), len(changed),
                  int(touch.sum()))
        if touch.any():
            near = _dilate(touch, int(np.ceil(3.0 * SIGMAS[0])))
            if not hopeless[touch].any():  # a push that failed there once is not tried again
                pushed = _push_clear(prob, trial, touch, prior, rate, box_margin, velocity_margin)
                if pushed is not None:
                    push += pushed - trial
                    x = pushed
                    ev = prob.evaluate(x, ev)
                    continue
                hopeless |= _dilate(touch, int(np.ceil(3.0 * SIGMAS[-1])))
            # no small push clears it: the widths that made it go back a step and stay there
            rows = np.flatnonzero(touch)
            culprit = np.zeros(n_groups, dtype=bool)
            for g in np.flatnonzero(bad[near].any(0)):  # the groups widened there this round
                back = level.copy()
                back[near, g] = np.maximum(back[near, g] - 1, 0)
                culprit[g] = not _touching(prob.robot, np.clip(_blend(prob, q, passes, back) + push, prob.lower, prob.upper), rows, prior).any()
            if not culprit.any():
                culprit[:] = True
            for g in np.flatnonzero(culprit):
                level[near, g] = np.maximum(level[near, g] - 1, 0)
                cap[near, g] = np.minimum(cap[near, g], level[near, g])
            trial = np.clip(_blend(prob, q, passes, level) + push, prob.lower, prob.upper)
            changed = np.flatnonzero(np.abs(trial - x).max(1) > 0)
            if _touching(prob.robot, trial, changed, prior).any():
                continue
        x = trial
        ev = prob.evaluate(x, ev)
    # the least share of each region's change that still passes
    pad = 3 * BAND + 2
    for a, b in _runs(np.abs(x - q).max(1) > 0):
        lo, hi = max(a - pad, 0), min(b + pad, len(q))
        if prob.failing(ev)[lo:hi].any():
            continue
        for share in SHARES:
            trial = x.copy()
            trial[a:b] = q[a:b] + share * (x[a:b] - q[a:b])
            ev_t = prob.evaluate(trial, ev)
            if prob.failing(ev_t)[lo:hi].any():
                continue
            if _touching(prob.robot, trial, np.arange(a, b), prior).any():
                continue
            x, ev = trial, ev_t
            break
    return x, ev


def _enforce(robot: Robot, q: np.ndarray, rate: float, limits: DynamicsLimits, box_margin: float,
             velocity_margin: float, touching: np.ndarray | None) -> tuple[np.ndarray, bool]:
    """`enforce_dynamics`' solve: the start low-passes the whole upper body (arms, fingers,
    waist) around a failing sample; where that leaves samples failing, the solve is run again
    low-passing only the joint groups at fault, and the result with fewer failing samples kept.
    Why both: low-passing one limb alone moves it against the other limb and the body, so a
    two-handed sign whose hands the contact repair kept 2 mm apart touches again (synth seqs 0
    and 8: the limb's low-pass is capped there and the torque stays over), while low-passing all
    of them keeps their relative motion; where contacts bound the whole upper body's low-pass
    instead, the limb at fault alone can still pass (synth seq 14)."""
    x, ok, failing = _enforce_with(robot, q, rate, limits, box_margin, velocity_margin, touching, True)
    if ok or not failing:
        return x, ok
    x2, ok2, failing2 = _enforce_with(robot, q, rate, limits, box_margin, velocity_margin, touching, False)
    return (x2, ok2) if (ok2, -failing2) > (ok, -failing) else (x, ok)


def _enforce_with(robot: Robot, q: np.ndarray, rate: float, limits: DynamicsLimits, box_margin: float,
                  velocity_margin: float, touching: np.ndarray | None, whole: bool
                  ) -> tuple[np.ndarray, bool, int]:
    """The solve with the start's low-pass on the whole upper body (`whole`) or on the joint
    groups at fault; the result, whether every limit holds, and its failing samples."""
    prob = _Problem(robot, q, rate, limits, box_margin, velocity_margin, whole)
    x, failing = _solve(prob, robot, q, rate, limits, box_margin, velocity_margin, touching)
    return x, failing == 0, failing


def _solve(prob: "_Problem", robot: Robot, q: np.ndarray, rate: float, limits: DynamicsLimits,
           box_margin: float, velocity_margin: float, touching: np.ndarray | None) -> tuple[np.ndarray, int]:
    """One start and Gauss-Newton refinement on `prob`: the result and its failing samples."""
    ev = prob.evaluate(q)
    failing_q = int(prob.failing(ev).sum())
    if not failing_q:
        return q, 0
    reach = max(1, int(round(REACH_S * rate)))
    prior = np.zeros(len(q), dtype=bool) if touching is None else np.asarray(touching, dtype=bool)
    x, ev = _local_start(prob, q, ev, prior, rate, box_margin, velocity_margin)
    log.debug("start: %d changed, %d failing", int((np.abs(x - q).max(1) > 0).sum()),
              int(prob.failing(ev).sum()))
    if not prob.failing(ev).any():
        return x, 0
    start_x = x
    bad = prob.failing(ev) | (np.abs(x - q).max(1) > 0)
    free = _dilate(bad, reach)
    nm = len(prob.movable)
    cost = prob.cost(x, ev)
    prob.watch_near(x, free)
    start = 1.0
    n = len(q)  # Δ² of the correction over the whole sequence: the held samples' is 0
    smooth = sp.diags([np.ones(n - 2), -2 * np.ones(n - 2), np.ones(n - 2)], [0, 1, 2], shape=(n - 2, n)).tocsc()
    for _ in range(ITERATIONS):
        rows = prob.rows(x, ev, free)
        a, r = rows.matrix(int(free.sum()) * nm)
        if not len(r):
            break
        idx = np.flatnonzero(free)
        d = (x - q)[idx][:, prob.movable]
        w = np.tile(prob.weight, len(idx))
        nf = len(idx)
        ss = sp.kron(smooth[:, idx].T @ smooth[:, idx], sp.eye(nm)) * W_SMOOTH
        h = W_HINGE * (a.T @ a) + sp.diags(w + 1e-9) + ss
        g = W_HINGE * (a.T @ r) + w * d.ravel() + ss @ d.ravel()
        direction = _solve_banded(h, -g).reshape(nf, nm)
        direction *= min(1.0, MAX_STEP / max(float(np.abs(direction).max()), 1e-12))
        accepted, scale = False, start
        for _try in range(BACKTRACK):
            trial = x.copy()
            trial[np.ix_(idx, prob.movable)] = np.clip(trial[idx][:, prob.movable] + scale * direction,
                                                       prob.lower[prob.movable], prob.upper[prob.movable])
            ev_t = prob.evaluate(trial, ev)
            c_t = prob.cost(trial, ev_t)
            log.debug("trial scale %.3g cost %.6g -> %.6g", scale, cost, c_t)
            if c_t < cost:
                # MuJoCo's verdict on what moved: a step that pushes a sample into a contact is
                # no step (the correction is never paid for with a contact)
                changed = np.flatnonzero(np.abs(trial - x).max(1) > 0)
                hits = _touching(robot, trial, changed, prior)
                if not hits.any():
                    accepted = True
                    start = min(1.0, 2.0 * scale)  # the next direction starts near this one's length
                    break
                log.debug("trial touches at %s", changed[hits][:8])
                prob.watch.update(int(t) for t in changed[hits])  # their contacts are rows now
            scale *= 0.5
        if not accepted:
            break
        x, ev, cost = trial, ev_t, c_t
        log.debug("rows %d cost %.4g free %d", len(r), cost, int(free.sum()))
        if not prob.failing(ev).any():
            break
        grown = free | _dilate(prob.failing(ev), reach)
        if (grown != free).any():
            prob.watch_near(x, grown & ~free)
        free = grown
    vmax = robot.velocity_limits * (1.0 - velocity_margin)
    if velocity_violations(x, vmax, rate):
        clamped = clamp_velocity(x, vmax, rate)
        changed = np.flatnonzero(np.abs(clamped - x).max(1) > 0)
        if _touching(robot, clamped, changed, prior).any():
            # never a contact for a torque: the start if it keeps the velocity limits, else the
            # input, whose verdict is the caller's
            if velocity_violations(start_x, vmax, rate):
                return q, failing_q
            return start_x, int(prob.failing(prob.evaluate(start_x)).sum())
        x, ev = clamped, prob.evaluate(clamped)
    return x, int(prob.failing(ev).sum())
