"""Dex3 finger retargeting on the synthetic lexicon's handshapes (fist, flat, pinch, point, C, Y)
given with absolute and with relative (mean-offset) hands: the thumb carries information."""

import numpy as np
import pytest

from embody.io.hands import absolute_to_relative, relative_to_absolute
from embody.retarget.hands import OPPOSE_RANGE, retarget_hands
from embody.robot import load_robot
from embody.synth.handshapes import handshape

SHAPES = ("fist", "flat", "pinch", "point", "c", "y", "relaxed")


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _pose(shape: str) -> np.ndarray:
    pose = np.zeros((1, 55, 3))
    pose[0, 25:40], pose[0, 40:55] = handshape(shape, "left"), handshape(shape, "right")
    return pose


def _fractions(robot, q, names, side):
    """How far each robot finger is from open (0) to its limit (1); thumb_0 = opposition."""
    def frac(joint):
        j = robot.joint_index(joint)
        v = q[0, names.index(joint)]
        limit = robot.upper[j] if v >= 0 else robot.lower[j]
        return abs(v / limit) / (OPPOSE_RANGE if "thumb_0" in joint else 1.0) if limit else 0.0
    return {"index": np.mean([frac(f"{side}_hand_index_{k}_joint") for k in (0, 1)]),
            "middle": np.mean([frac(f"{side}_hand_middle_{k}_joint") for k in (0, 1)]),
            "thumb": np.mean([frac(f"{side}_hand_thumb_{k}_joint") for k in (1, 2)]),
            "opposition": frac(f"{side}_hand_thumb_0_joint")}


@pytest.mark.parametrize("convention", ["absolute", "relative"])
@pytest.mark.parametrize("side", ["left", "right"])
def test_handshapes_in_both_conventions(robot, side, convention):
    out = {}
    for shape in SHAPES:
        pose = _pose(shape)
        if convention == "relative":  # what a SOKE/SignAvatars file holds, converted on load
            relative = absolute_to_relative(pose)
            assert not np.allclose(relative, pose)  # the file's numbers really differ
            pose = relative_to_absolute(relative).astype(np.float64)
        q, names = retarget_hands(pose, robot)
        cols = [robot.joint_index(n) for n in names]
        assert q.shape == (1, 14) and np.all(q >= robot.lower[cols]) and np.all(q <= robot.upper[cols])
        out[shape] = _fractions(robot, q, names, side)
    assert all(out["fist"][f] > 0.8 for f in ("index", "middle")) and out["fist"]["opposition"] > 0.9
    assert all(v < 0.15 for v in out["flat"].values())
    assert out["point"]["index"] < 0.05 and out["point"]["middle"] > 0.8
    assert 0.3 < out["pinch"]["index"] < 0.8 and out["pinch"]["opposition"] > 0.6
    assert 0.3 < out["c"]["index"] < 0.8 and 0.2 < out["c"]["thumb"] < 0.8
    assert out["y"]["thumb"] < 0.05 and out["y"]["opposition"] < 0.05 and out["y"]["index"] > 0.8
    # the thumb is not saturated for a relaxed hand, and opposition is driven, in order
    assert 0.2 < out["relaxed"]["thumb"] < 0.8 and 0.2 < out["relaxed"]["opposition"] < 0.9
    order = [out[s]["opposition"] for s in ("y", "flat", "c", "pinch", "fist")]
    assert order == sorted(order) and len(set(np.round(order, 3))) == 5


def test_opposition_brings_the_thumb_to_the_fingers(robot):
    """On the robot's own landmarks: a pinch brings thumb and index tips together; a Y keeps them apart."""
    gaps = {}
    for shape in ("y", "pinch"):
        q_hand, names = retarget_hands(_pose(shape), robot)
        q = robot.tpose.copy()
        q[[robot.joint_index(n) for n in names]] = q_hand[0]
        p, _, _ = robot.landmark_points(q[None], ["right_thumb_tip", "right_index_tip"])
        gaps[shape] = np.linalg.norm(p[0, 0] - p[0, 1])
    assert gaps["pinch"] < gaps["y"] - 0.02
