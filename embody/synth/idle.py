"""A clip with no collision at all: the reference input for "a clip that needs no work costs
next to nothing" (the collision step's test and `benchmarks/long_sequence.py`)."""

from __future__ import annotations

import numpy as np

from embody.motion import JOINT_NAMES, Motion


def idle_motion(frames: int = 600, fps: float = 120.0) -> Motion:
    """Arms held out to the sides, swaying slowly: no body part near another."""
    j = JOINT_NAMES.index
    s = np.sin(np.linspace(0, 2 * np.pi, frames))
    pose = np.zeros((frames, 55, 3))
    pose[:, j("left_shoulder"), 2] = -0.3 + 0.05 * s
    pose[:, j("right_shoulder"), 2] = 0.3 - 0.05 * s
    pose[:, j("left_elbow"), 1] = -0.2
    pose[:, j("right_elbow"), 1] = 0.2
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=fps)
