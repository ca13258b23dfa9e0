"""Retargeting: shape fit, targets, whole-sequence IK, hands and MuJoCo verification."""

from __future__ import annotations

from embody.body.base import BodyModel
from embody.config.ik import IKConfig
from embody.motion import Motion
from embody.retarget.ik import IKSolution
from embody.retarget.shape_fit import ShapeFit, shape_fit
from embody.retarget.targets import Targets, build_targets
# The public solver: whole-sequence IK, in overlapping windows past `ik.window_frames` so memory
# follows the window (the critic's re-solves and the fidelity baseline go through it too).
from embody.retarget.windows import solve_windowed as solve
from embody.robot import Robot

__all__ = ["IKSolution", "ShapeFit", "Targets", "build_targets", "retarget", "shape_fit", "solve"]


def retarget(motion: Motion, robot: Robot, body: BodyModel, fit: ShapeFit | None = None,
             cfg: IKConfig | None = None, init: IKSolution | None = None) -> tuple[Targets, IKSolution]:
    """Motion → (targets, IK solution) with the (cached) shape fit."""
    cfg = cfg or IKConfig()
    fit = fit or shape_fit(robot, body, cfg)
    targets = build_targets(motion, body, fit, robot, cfg)
    return targets, solve(robot, targets, cfg, init=init)
