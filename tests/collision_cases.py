"""Built collision poses and the module fixtures shared by the collision tests (not a test
module; a test module imports the fixtures it uses)."""

from __future__ import annotations

import numpy as np
import pytest

from embody.body import MannequinBody
from embody.collision import collision_model

from embody.motion import JOINT_NAMES

J = JOINT_NAMES.index


def crossing_poses() -> np.ndarray:
    """Arms down into the hips, hands through the chest, hands clasped, fingers curled."""
    pose = np.zeros((5, 55, 3))
    pose[1, J("left_shoulder"), 2], pose[1, J("right_shoulder"), 2] = -1.6, 1.6
    for t, bend in ((2, 2.4), (3, 2.0)):
        pose[t, J("left_shoulder")] = (0.0, -1.0, -0.3)
        pose[t, J("right_shoulder")] = (0.0, 1.0, 0.3)
        pose[t, J("left_elbow"), 1], pose[t, J("right_elbow"), 1] = -bend, bend
    pose[4] = pose[3]
    pose[4, 25:40, 2], pose[4, 40:55, 2] = -1.2, 1.2
    return pose


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


@pytest.fixture(scope="module")
def model(body):
    return collision_model(body, vertex_stride=4)
