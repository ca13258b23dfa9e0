"""Finger retargeting: SMPL-X finger rotations → robot hand joints by curl matching.

Each human finger is reduced to a curl fraction in [0, 1] (0 = flat, 1 = fully closed), so a
handshape reads the same on a hand with fewer fingers. Curl of a long finger is the sum of its
three joints' flexion, i.e. the axis-angle component about the flexion axis (−z for the left
hand, +z for the right: with flat palms down in the T-pose, fingers curl towards −y). The thumb's
flexion axis varies with opposition, so its curl is the summed rotation magnitude.

| robot finger (Dex3) | robot joints (base → tip)            | human source                      |
|---------------------|--------------------------------------|-----------------------------------|
| thumb               | thumb_0 (rotation), thumb_1, thumb_2 | thumb1-3 curl (thumb_0 kept at 0) |
| index               | index_0 ← MCP, index_1 ← PIP+DIP     | index1 ; index2+index3            |
| middle              | middle_0 ← MCP, middle_1 ← PIP+DIP   | mean of middle, ring and pinky    |

A joint's value is `curl × closed`, with `closed` its limit farther from zero (the closing
direction on both Dex3 hands), so outputs are always within the limits.
"""

from __future__ import annotations

import numpy as np

from embody.motion import JOINT_NAMES
from embody.robot import Robot

#: Human flexion (rad) that counts as fully closed: MCP, PIP+DIP and the whole thumb.
FULL_MCP = 1.5
FULL_DISTAL = 2.6
FULL_THUMB = 2.0
_AXIS = {"left": np.array([0.0, 0.0, -1.0]), "right": np.array([0.0, 0.0, 1.0])}


def _joint(side: str, name: str) -> int:
    return JOINT_NAMES.index(f"{side}_{name}")


def finger_curls(pose: np.ndarray, side: str) -> dict[str, np.ndarray]:
    """Per-frame curl fractions (T,) of thumb, index (mcp, distal) and merged middle for one hand.

    `pose` is the (T,55,3) axis-angle SMPL-X pose with absolute hands (flat = zero).
    """
    axis = _AXIS[side]

    def flex(name: str) -> np.ndarray:
        return pose[:, _joint(side, name)] @ axis

    def long_finger(f: str) -> tuple[np.ndarray, np.ndarray]:
        mcp = np.clip(flex(f"{f}1") / FULL_MCP, 0.0, 1.0)
        distal = np.clip((flex(f"{f}2") + flex(f"{f}3")) / FULL_DISTAL, 0.0, 1.0)
        return mcp, distal

    index = long_finger("index")
    rest = [long_finger(f) for f in ("middle", "ring", "pinky")]
    thumb = sum(np.linalg.norm(pose[:, _joint(side, f"thumb{i}")], axis=-1) for i in (1, 2, 3))
    return {"thumb": np.clip(thumb / FULL_THUMB, 0.0, 1.0),
            "index_mcp": index[0], "index_distal": index[1],
            "middle_mcp": np.mean([r[0] for r in rest], axis=0),
            "middle_distal": np.mean([r[1] for r in rest], axis=0)}


def _closed(robot: Robot, name: str) -> float:
    j = robot.joint_index(name)
    lo, hi = robot.lower[j], robot.upper[j]
    return float(hi if abs(hi) >= abs(lo) else lo)


def retarget_hands(pose: np.ndarray, robot: Robot) -> tuple[np.ndarray, list[str]]:
    """Robot hand joint values (T, n_hand) and their names; (T, 0) for robots without hands."""
    pose = np.asarray(pose, dtype=np.float64)
    columns: list[np.ndarray] = []
    names: list[str] = []
    for side in ("left", "right"):
        fingers = robot.spec.hands.get(side)
        if not fingers:
            continue
        curls = finger_curls(pose, side)
        sources = {
            "thumb": [np.zeros(len(pose)), curls["thumb"], curls["thumb"]],
            "index": [curls["index_mcp"], curls["index_distal"]],
            "middle": [curls["middle_mcp"], curls["middle_distal"]],
        }
        for finger in ("thumb", "index", "middle"):
            for jn, curl in zip(fingers.get(finger, []), sources[finger]):
                j = robot.joint_index(jn)
                value = curl * _closed(robot, jn)
                columns.append(np.clip(value, robot.lower[j], robot.upper[j]))
                names.append(jn)
    q = np.stack(columns, axis=1) if columns else np.zeros((len(pose), 0))
    return q, names
