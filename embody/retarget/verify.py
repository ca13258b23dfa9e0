"""MuJoCo verification of a joint trajectory as a per-frame table plus aggregates.

`solve` already stores these aggregates in `IKSolution.metrics`; this re-checks any trajectory
(a refined one, or a plain q array) against targets.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from embody.retarget.ik import IKSolution, evaluate
from embody.retarget.targets import Targets
from embody.robot import Robot
from embody.robot.contacts import self_collision_contacts

__all__ = ["self_collision_contacts", "verify"]


def verify(robot: Robot, solution: IKSolution | np.ndarray, targets: Targets) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Per-frame metrics table and aggregates (self-collision frames should be 0)."""
    q = solution.q if isinstance(solution, IKSolution) else np.asarray(solution)
    frames, metrics = evaluate(robot, q, targets)
    table = pd.DataFrame({
        "wrist_pos_err_mm_left": frames["wrist_pos_err_mm"][:, 0],
        "wrist_pos_err_mm_right": frames["wrist_pos_err_mm"][:, 1],
        "wrist_rot_err_deg_left": frames["wrist_rot_err_deg"][:, 0],
        "wrist_rot_err_deg_right": frames["wrist_rot_err_deg"][:, 1],
        "elbow_pos_err_mm_left": frames["elbow_pos_err_mm"][:, 0],
        "elbow_pos_err_mm_right": frames["elbow_pos_err_mm"][:, 1],
        "self_contacts": frames["self_contacts"],
    })
    return table, dict(metrics)
