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
from embody.retarget.ik import IKSolution, finish_solution, solve, solve_joints
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
    # a cross-fade of two collision-free windows can collide: the repair runs on the blend
    return finish_solution(robot, robot.clip(q), targets, cfg, {"windows": float(len(spans))})
