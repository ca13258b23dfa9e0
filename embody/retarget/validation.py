"""Validity counters of a joint trajectory, independent of the targets it was solved for.

What a robot may execute: no joint-limit violations, no velocity-limit violations at the
trajectory's rate, no penetrating self-contacts in MuJoCo, and no inverse-dynamics torque over a
motor's effort limit (`torque_viol`: fixed base, free motion, along the natural cubic spline
through the samples that the export commands, dry friction included; `robot.dynamics`), at every sample of q exactly as
given (float64; a float32 file is validated after its cast). The pipeline's metrics step stores
them for the exported control-rate array, and the report and the library export read them; the
export also recomputes them on each file it writes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from embody.verdicts import VALIDATION_KEYS  # noqa: E402  (the export rule lives there)


def validation_counts(robot: Any, q: np.ndarray, fps: float,
                      contacts: np.ndarray | None = None) -> dict[str, float]:
    """Counts of limit violations, velocity violations, MuJoCo self-collision frames and (sample,
    joint) torques over the effort limit (`torque_viol`) of q (T,n).
    `contacts` (T,): MuJoCo's per-sample contact counts of exactly this q, when already known."""
    from embody.retarget.limits import limit_violations, velocity_violations
    from embody.robot.contacts import self_collision_contacts

    q = np.asarray(q, dtype=np.float64)
    contacts = self_collision_contacts(robot, q) if contacts is None else contacts
    return {"joint_limit_violations": float(limit_violations(q, robot.lower, robot.upper)),
            "velocity_violations": float(velocity_violations(q, robot.velocity_limits, fps)),
            "self_collision_frames": float((np.asarray(contacts) > 0).sum()),
            "torque_viol": float(torque_violations(robot, q, fps))}


def torque_violations(robot: Any, q: np.ndarray, fps: float, tol: float = 1e-9) -> int:
    """Number of (sample, joint) pairs whose inverse-dynamics torque exceeds the effort limit."""
    from embody.robot.dynamics import effort_limits, inverse_dynamics

    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if len(q) < 2:
        return 0
    limit = effort_limits(robot)
    return int((np.abs(inverse_dynamics(robot, q, 1.0 / fps)) > limit * (1 + tol) + tol).sum())
