"""What the physics replay says about one exported trajectory.

Measured against the reference itself (the exported 50 Hz array's kinematic palm and fingertip
positions) and against the human (sign fidelity of the simulated motion, the same `compare_with`
the metrics step uses on the kinematic array). Inputs of the physics-valid verdict:
torque over the limit (inverse dynamics of the exported array), saturated control steps (fixed-
base replay), palm tracking p95, self-contacts of the simulated motion, the ZMP margin (cart-table
model of the standing robot) and whether the standing replay stays up.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from embody.physics.actuation import actuation
from embody.physics.commands import Commands, commands
from embody.physics.replay import StandingReplay, reference, replay_fixed, replay_standing, standing_model
from embody.robot.contacts import contact_pairs, self_collision_contacts
from embody.robot.dynamics import center_of_mass, polygon_margin, stance_pose, support_polygon, zmp
from embody.robot.exclusions import ancestors, hand_roots
from embody.robot.model import Robot
from embody.verdicts import PHYSICS_RULE, physics_valid

#: The ZMP must stay at least this far inside the feet's polygon (m): the verdict's bound.
ZMP_MARGIN = PHYSICS_RULE["zmp_margin_min_mm"][1] / 1000.0


@dataclass(frozen=True)
class StandingBounds:
    """When the standing robot "stays up", derived from the one margin the ZMP rule budgets
    (`ZMP_MARGIN`, δ) and the stance's CoM height h above the floor: the ZMP analysis assumes
    the robot stands rigidly where the stance puts it, so the simulated robot must stay there
    within δ. The whole-body CoM within δ (horizontally) of where the rigid stance puts it, and
    the pelvis no more than δ lower; each foot slides at most δ (the support polygon moves by
    less than the margin); the pelvis and each foot tilt at most δ/h (a rigid tilt about the
    feet by that angle moves the CoM by δ); no foot contact point rises more than the foot's
    length × δ/h (a foot tilted by δ/h about one edge lifts its far edge that much)."""

    com_offset: float  # m
    pelvis_drop: float  # m
    foot_slip: float  # m
    tilt: float  # rad, pelvis and feet
    foot_lift: float  # m
    com_height: float  # m, for the record


def standing_bounds(robot: Robot) -> StandingBounds:
    """`StandingBounds` of the robot's stance (cached on the robot)."""
    key = "physics.standing_bounds"
    if key not in robot.derived:
        stand = stance_pose(robot)
        _, floor = support_polygon(robot, stand)
        height = float(center_of_mass(robot, stand[None])[0, 2] - floor)
        tilt = ZMP_MARGIN / height
        rm, qpos0, feet = standing_model(robot)
        length = _foot_length(rm.model, rm.model.geom_bodyid[feet], qpos0, feet)
        robot.derived[key] = StandingBounds(com_offset=ZMP_MARGIN, pelvis_drop=ZMP_MARGIN,
                                            foot_slip=ZMP_MARGIN, tilt=tilt, foot_lift=length * tilt,
                                            com_height=height)
    return robot.derived[key]


def _foot_length(model: mujoco.MjModel, owner: np.ndarray, qpos: np.ndarray, feet: np.ndarray) -> float:
    """The longest distance between two contact geoms of one foot at the stance (m)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    best = 0.0
    for b in np.unique(owner):
        p = data.geom_xpos[feet[owner == b], :2]
        best = max(best, float(np.max(np.linalg.norm(p[:, None] - p[None], axis=-1))))
    return best


def standing_metrics(robot: Robot, stand: StandingReplay) -> dict[str, Any]:
    """The standing replay's figures and whether the robot stays up (`StandingBounds`)."""
    b = standing_bounds(robot)
    figures = {"com_offset": stand.com_offset.max(), "pelvis_drop": stand.pelvis_drop.max(),
               "foot_slip": stand.foot_slip.max(), "pelvis_tilt": stand.pelvis_tilt.max(),
               "foot_tilt": stand.foot_tilt.max(), "foot_lift": stand.foot_lift.max()}
    bound = {"com_offset": b.com_offset, "pelvis_drop": b.pelvis_drop, "foot_slip": b.foot_slip,
             "pelvis_tilt": b.tilt, "foot_tilt": b.tilt, "foot_lift": b.foot_lift}
    holds = all(figures[k] <= bound[k] for k in figures)
    polygon, _ = support_polygon(robot, stance_pose(robot))
    support = stand.support
    out: dict[str, Any] = {"standing_holds": bool(holds)}
    for k in ("com_offset", "pelvis_drop", "foot_slip", "foot_lift"):
        out[f"standing_{k}_max_mm"] = float(figures[k] * 1000.0)
    out["standing_pelvis_drift_max_mm"] = float(stand.pelvis_drift.max() * 1000.0)
    for k in ("pelvis_tilt", "foot_tilt"):
        out[f"standing_{k}_max_deg"] = float(np.rad2deg(figures[k]))
    r = stand.rollout
    out["standing_saturated_step_pct"] = 100.0 * float((np.abs(r.demand) >= r.limit * (1 - 1e-9)).any(1).mean())
    out["zmp_multibody_margin_min_mm"] = float(polygon_margin(support.zmp, polygon).min() * 1000.0)
    fz = np.maximum(support.force[:, 2], 1e-9)
    out["floor_friction_ratio_max"] = float((np.linalg.norm(support.force[:, :2], axis=1) / fz).max())
    out["floor_yaw_moment_max_nm"] = float(np.abs(support.yaw_moment).max())
    return out


def sim_contacts(robot: Robot, q: np.ndarray) -> tuple[dict[str, Any], Counter]:
    """Self-contacts of the simulated motion q (T,n) under the kinematic check's own rule
    (`contacts.self_collision_contacts`: the same counted geom pairs, the robot YAML's
    documented `ignore_pairs` left out, any penetration): the samples with one, and per kind of
    body pair (both in one hand, one in each hand, a hand against the rest of the body, other)
    its pair-samples (a sample counts once per penetrating body pair); and the pair-samples
    per body pair (names sorted)."""
    hit = np.flatnonzero(self_collision_contacts(robot, q) > 0)
    pairs = contact_pairs(robot, q[hit]) if len(hit) else Counter()
    out: dict[str, Any] = {"sim_contact_samples": int(len(hit))}
    kinds = dict.fromkeys(("same_hand", "two_hands", "hand_body", "other"), 0)
    hand_of = _hand_of_body(robot)
    for (a, b), n in pairs.items():
        kinds[_pair_kind(hand_of, a, b)] += n
    out.update({f"sim_contact_pairs.{k}": v for k, v in kinds.items()})
    return out, pairs


def _hand_of_body(robot: Robot) -> dict[str, int]:
    """Body name → index of the hand it belongs to (bodies under a hand's root; cached)."""
    key = "physics.hand_of_body"
    if key in robot.derived:
        return robot.derived[key]
    m = robot.model
    out: dict[str, int] = {}
    for i, root in enumerate(hand_roots(m, robot.spec)):
        for b in range(m.nbody):
            if root in ancestors(m, b):
                out[m.body(b).name] = i
    robot.derived[key] = out
    return out


def _pair_kind(hand_of: dict[str, int], a: str, b: str) -> str:
    ha, hb = hand_of.get(a), hand_of.get(b)
    if ha is not None and ha == hb:
        return "same_hand"
    if ha is not None and hb is not None:
        return "two_hands"
    if ha is not None or hb is not None:
        return "hand_body"
    return "other"


@dataclass
class PhysicsResult:
    """Scalars (`metrics`, stored as attrs) and per-sample series (`arrays`, at the export's rate)."""

    metrics: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return dict(self.arrays)

    def to_attrs(self) -> dict[str, Any]:
        return {"metrics": self.metrics}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "PhysicsResult":
        return cls(dict(attrs.get("metrics", {})), {k: np.asarray(v) for k, v in arrays.items()})


def _stats(err_mm: np.ndarray, name: str) -> dict[str, float]:
    e = np.asarray(err_mm, dtype=np.float64).ravel()
    if not e.size:
        return {}
    return {f"{name}_mean_mm": float(e.mean()), f"{name}_p95_mm": float(np.percentile(e, 95)),
            f"{name}_max_mm": float(e.max())}


def evaluate(robot: Robot, q: np.ndarray, fps: float, human: Any = None, fidelity_cfg: Any = None,
             cmd: Commands | None = None) -> PhysicsResult:
    """Replay the exported array q (T,n) at `fps` (or its `cmd` as read from a file) and measure.

    `human` (a `Track` at `fps`) and `fidelity_cfg`: when given, sign fidelity of the simulated
    motion (`physics.fidelity.*`)."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    cmd = commands(robot, q, fps) if cmd is None else cmd
    act = actuation(robot)
    # torque the exported array itself needs (inverse dynamics at its own rate)
    ratio = np.abs(cmd.tau_ff) / act.limit  # (T,n)
    over = ratio > 1.0
    out: dict[str, Any] = {"samples": int(len(q)), "control_rate_hz": act.control_rate_hz,
                           "torque_over_samples": int(over.any(1).sum()),
                           "torque_over_joint_samples": int(over.sum()),
                           "torque_ratio_max": float(ratio.max(initial=0.0))}
    # fixed-base replay (the reference at the control rate serves both replays)
    ref = reference(robot, cmd)
    fixed = replay_fixed(robot, cmd, ref)
    r = fixed.rollout
    sat = np.abs(r.demand) >= r.limit * (1.0 - 1e-9)
    out["control_steps"] = int(len(r.q))
    out["saturated_steps"] = int(sat.any(1).sum())
    out["saturated_step_pct"] = 100.0 * out["saturated_steps"] / max(1, len(r.q))
    demand_ratio = np.abs(r.demand) / r.limit
    for g, name in enumerate(act.group_names):
        cols = act.group[r.joints] == g
        if cols.any():
            out[f"demand_ratio_max.{name}"] = float(demand_ratio[:, cols].max())
        ids = act.group == g
        out[f"torque_ratio_max.{name}"] = float(ratio[:, ids].max(initial=0.0))
    duration = max((len(r.q) - 1) * r.dt, r.dt)
    out["energy_j_per_s"] = float(np.abs(r.torque * r.qd).sum() * r.dt / duration)
    # tracking: simulated vs reference landmarks (palms, fingertips), torso frame
    names = [n for n in robot.spec.landmarks if n.endswith("_palm") or n.endswith("_tip")]
    pts, _, _ = robot.landmark_points(np.concatenate([q, fixed.q50]), names)  # one FK for both
    ref_pts, sim_pts = pts[: len(q)], pts[len(q):]
    err = np.linalg.norm(sim_pts - ref_pts, axis=-1) * 1000.0  # (T,K) mm
    palm = np.array([n.endswith("_palm") for n in names])
    out.update(_stats(err[:, palm], "palm_err"))
    out.update(_stats(err[:, ~palm], "fingertip_err"))
    contact_figures, _ = sim_contacts(robot, fixed.q50)
    out.update(contact_figures)
    # joint tracking per group: what the contacts and palm errors come from
    err_q = np.abs(fixed.q50 - q)[:, r.joints]  # at the samples
    for g, name in enumerate(act.group_names):
        cols = act.group[r.joints] == g
        if cols.any():
            out[f"joint_err_max_deg.{name}"] = float(np.rad2deg(err_q[:, cols].max()))
    # balance: cart-table ZMP of the exported array, standing replay
    point, _, margin = zmp(robot, q, 1.0 / fps)
    out["zmp_margin_min_mm"] = float(margin.min() * 1000.0)
    out["zmp_outside_samples"] = int((margin < 0).sum())
    out["zmp_short_samples"] = int((margin < ZMP_MARGIN).sum())
    out.update(standing_metrics(robot, replay_standing(robot, cmd, ref)))
    if human is not None and fidelity_cfg is not None:
        from embody.metrics.embodiments import scored_robot_track
        from embody.metrics.fidelity import compare_with
        track = scored_robot_track(robot, fixed.q50, fps, human, fidelity_cfg)
        _, fid = compare_with(human, track, fidelity_cfg)
        out.update({f"fidelity.{k}": v for k, v in fid.items()})
    out["palm_landmarks"] = int(palm.sum())
    out["valid"] = physics_valid(out)
    arrays = {"torque_ratio": ratio.max(1).astype(np.float32),
              "palm_err_mm": err[:, palm].max(1).astype(np.float32) if palm.any() else np.zeros(len(q), np.float32),
              "zmp": point.astype(np.float32), "zmp_margin": margin.astype(np.float32),
              "q_sim": fixed.q50}
    return PhysicsResult(out, arrays)
