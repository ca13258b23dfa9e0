"""Dex3 finger retargeting on four handshapes built as SMPL-X finger poses."""

import numpy as np
import pytest

from embody.config.robot import RobotConfig
from embody.motion import JOINT_NAMES
from embody.retarget.hands import retarget_hands
from embody.robot import load_robot

_FLEX_AXIS = {"left": np.array([0.0, 0.0, -1.0]), "right": np.array([0.0, 0.0, 1.0])}


def _hand_pose(side: str, curled: dict[str, float]) -> np.ndarray:
    """One frame (1,55,3): each named finger flexed by `angle` at all three joints."""
    pose = np.zeros((1, 55, 3))
    for finger, angle in curled.items():
        for i in (1, 2, 3):
            j = JOINT_NAMES.index(f"{side}_{finger}{i}")
            if finger == "thumb":  # thumb opposes across the palm
                pose[0, j] = np.array([0.0, 1.0, 0.0]) * angle
            else:
                pose[0, j] = _FLEX_AXIS[side] * angle
    return pose


SHAPES = {
    "fist": {f: 1.3 for f in ("index", "middle", "ring", "pinky")} | {"thumb": 0.8},
    "flat": {},
    "point": {f: 1.3 for f in ("middle", "ring", "pinky")} | {"thumb": 0.8},
    "pinch": {"index": 0.7, "thumb": 0.5},
}


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _fraction(robot, q, names, joint):
    """How closed a joint is: 0 open, 1 at its closing limit."""
    j = robot.joint_index(joint)
    closed = robot.upper[j] if abs(robot.upper[j]) >= abs(robot.lower[j]) else robot.lower[j]
    return q[0, names.index(joint)] / closed


@pytest.mark.parametrize("side", ["left", "right"])
def test_handshapes(robot, side):
    out = {}
    for shape, curls in SHAPES.items():
        q, names = retarget_hands(_hand_pose(side, curls), robot)
        assert q.shape == (1, 14)
        cols = [robot.joint_index(n) for n in names]
        assert np.all(q >= robot.lower[cols]) and np.all(q <= robot.upper[cols])
        out[shape] = {f: np.mean([_fraction(robot, q, names, f"{side}_hand_{f}_{k}_joint") for k in ks])
                      for f, ks in (("index", (0, 1)), ("middle", (0, 1)), ("thumb", (1, 2)))}
    assert all(v > 0.8 for v in out["fist"].values())
    assert all(v < 0.05 for v in out["flat"].values())
    assert out["point"]["index"] < 0.05 and out["point"]["middle"] > 0.8
    assert 0.3 < out["pinch"]["index"] < 0.8 and out["pinch"]["thumb"] > 0.5
    assert out["pinch"]["middle"] < 0.05


def test_robot_without_hands_skips():
    h1 = load_robot(RobotConfig(name="unitree_h1"))
    q, names = retarget_hands(_hand_pose("left", SHAPES["fist"]), h1)
    assert q.shape == (1, 0) and names == []
