"""What the physics replay says about one exported trajectory.

Measured against the reference itself (the exported 50 Hz array's kinematic palm and fingertip
positions) and against the human (sign fidelity of the simulated motion, the same `compare_with`
the metrics step uses on the kinematic array). Inputs of the physics-valid verdict:
torque over the limit (inverse dynamics of the exported array), saturated control steps (fixed-
base replay), palm tracking p95, self-contacts of the simulated motion, the ZMP margin (cart-table
model of the standing robot) and whether the standing replay stays up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from embody.physics.actuation import actuation
from embody.physics.commands import Commands, commands
from embody.physics.replay import replay_fixed, replay_standing
from embody.robot.contacts import collision_model
from embody.robot.dynamics import zmp
from embody.robot.model import Robot
from embody.verdicts import PHYSICS_RULE, physics_valid

#: A self-contact counts when two counted geoms are more than this far into each other (m).
PENETRATION = 0.001
#: Standing holds while the pelvis tilts at most this much (rad), drifts at most this far
#: horizontally and sinks at most this far (m), and each foot stays flat: tilts at most
#: FOOT_TILT and no contact point rises more than FOOT_LIFT.
PELVIS_TILT = np.deg2rad(10.0)
PELVIS_DRIFT = 0.05
PELVIS_DROP = 0.05
FOOT_TILT = np.deg2rad(5.0)
FOOT_LIFT = 0.005
#: The ZMP must stay at least this far inside the feet's polygon (m): the verdict's bound.
ZMP_MARGIN = PHYSICS_RULE["zmp_margin_min_mm"][1] / 1000.0


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


def penetrating_samples(robot: Robot, q: np.ndarray, depth: float = PENETRATION) -> np.ndarray:
    """Per sample (T,), counted self-contacts deeper than `depth` (the pairs `contacts` counts)."""
    model, counted = collision_model(robot)
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    out = np.zeros(len(q), dtype=np.int64)
    for t, qt in enumerate(np.atleast_2d(q)):
        data.qpos[robot.qpos_adr] = qt
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        if data.ncon:
            geom = data.contact.geom[: data.ncon]
            out[t] = int(np.sum((data.contact.dist[: data.ncon] < -depth) & counted[geom[:, 0], geom[:, 1]]))
    return out


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
    # fixed-base replay
    fixed = replay_fixed(robot, cmd)
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
    ref_pts, _, _ = robot.landmark_points(q, names)
    sim_pts, _, _ = robot.landmark_points(fixed.q50, names)
    err = np.linalg.norm(sim_pts - ref_pts, axis=-1) * 1000.0  # (T,K) mm
    palm = np.array([n.endswith("_palm") for n in names])
    out.update(_stats(err[:, palm], "palm_err"))
    out.update(_stats(err[:, ~palm], "fingertip_err"))
    contacts = penetrating_samples(robot, fixed.q50)
    out["sim_contact_samples"] = int((contacts > 0).sum())
    # balance: cart-table ZMP of the exported array, standing replay
    point, _, margin = zmp(robot, q, 1.0 / fps)
    out["zmp_margin_min_mm"] = float(margin.min() * 1000.0)
    out["zmp_outside_samples"] = int((margin < 0).sum())
    out["zmp_short_samples"] = int((margin < ZMP_MARGIN).sum())
    stand = replay_standing(robot, cmd)
    holds = bool(stand.pelvis_tilt.max() <= PELVIS_TILT and stand.pelvis_drift.max() <= PELVIS_DRIFT
                 and stand.pelvis_drop.max() <= PELVIS_DROP and stand.foot_tilt.max() <= FOOT_TILT
                 and stand.foot_lift.max() <= FOOT_LIFT)
    out.update({"standing_holds": holds,
                "standing_pelvis_tilt_max_deg": float(np.rad2deg(stand.pelvis_tilt.max())),
                "standing_pelvis_drift_max_mm": float(stand.pelvis_drift.max() * 1000.0),
                "standing_pelvis_drop_max_mm": float(stand.pelvis_drop.max() * 1000.0),
                "standing_foot_tilt_max_deg": float(np.rad2deg(stand.foot_tilt.max())),
                "standing_foot_lift_max_mm": float(stand.foot_lift.max() * 1000.0),
                "standing_saturated_step_pct": 100.0 * float(
                    (np.abs(stand.rollout.demand) >= stand.rollout.limit * (1 - 1e-9)).any(1).mean())})
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
