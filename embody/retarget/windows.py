"""Whole-sequence IK of long sequences in overlapping windows, so memory follows the window.

The solver holds per-frame Jacobians and normal blocks for every frame at once (~1.5 GB at
2,000 frames on G1 with hands). Frames couple only through the smoothness and velocity terms,
so windows of `ik.window_frames` sharing `ik.window_overlap` frames, cross-faded linearly over
the overlap, keep memory bounded. The blended trajectory is clipped, velocity-clamped and
evaluated as a whole, exactly as `solve` does for one window, and contact-repaired once on the
blend (the windows are raw optimiser output, `solve_joints`: a per-window repair and MuJoCo check
would be redone on the blend anyway).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from embody.collision.windows import windows
from embody.config.ik import IKConfig
from embody.retarget.control import control_trajectory_checked, separate_checked
from embody.retarget.validation import validation_counts
from embody.retarget.ik import IKSolution, evaluate, solve, solve_joints
from embody.retarget.limits import clamp_velocity
from embody.retarget.targets import _ARRAYS, Targets
from embody.robot import Robot


def _part(targets: Targets, start: int, end: int) -> Targets:
    return replace(targets, **{k: getattr(targets, k)[start:end] for k in _ARRAYS})


def solve_windowed(robot: Robot, targets: Targets, cfg: IKConfig | None = None,
                   init: IKSolution | np.ndarray | None = None) -> IKSolution:
    """`solve` per window of `cfg.window_frames` frames, cross-faded over `cfg.window_overlap`."""
    cfg = cfg or IKConfig()
    t = targets.num_frames
    spans = windows(t, cfg.window_frames, cfg.window_overlap)
    if len(spans) == 1:
        return solve(robot, targets, cfg, init)
    q0 = init.q if isinstance(init, IKSolution) else init
    if q0 is not None and np.shape(q0) != (t, robot.n_joints):
        q0 = None
    q = np.zeros((t, robot.n_joints))
    prev_end = 0
    for start, end in spans:
        # the optimiser only: the clamp, repair and MuJoCo verification run once, on the blend
        part = solve_joints(robot, _part(targets, start, end), cfg,
                            None if q0 is None else np.asarray(q0)[start:end])
        shared = max(0, prev_end - start)
        if shared:
            w = ((np.arange(shared) + 1) / (shared + 1))[:, None]
            q[start:start + shared] = (1 - w) * q[start:start + shared] + w * part[:shared]
        q[start + shared:end] = part[shared:]
        prev_end = end
    q = robot.clip(q)
    if cfg.enforce_velocity_limits:
        q = clamp_velocity(q, robot.velocity_limits, targets.fps)
    clear = False
    if cfg.contact_repair:  # a cross-fade of two collision-free windows can collide
        q, clear = separate_checked(robot, q, targets.fps, enforce_velocity=cfg.enforce_velocity_limits)
    frames, metrics = evaluate(robot, q, targets, np.zeros(len(q), np.int64) if clear else None)
    metrics["windows"] = float(len(spans))
    q_control, clear = control_trajectory_checked(robot, q, targets.fps, cfg.control_rate_hz,
                                                  cfg.contact_repair)
    metrics.update({f"control_{k}": v for k, v in validation_counts(
        robot, q_control, cfg.control_rate_hz, np.zeros(len(q_control), np.int64) if clear else None).items()})
    return IKSolution(q=q, joint_names=list(robot.joint_names), fps=targets.fps, q_control=q_control,
                      control_rate_hz=cfg.control_rate_hz, frame_metrics=frames, metrics=metrics)
