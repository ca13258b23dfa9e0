"""Finger retargeting: SMPL-X finger rotations → robot hand joints by curl matching.

Each human finger is reduced to a curl fraction in [0, 1] (0 = flat, 1 = fully closed), so a
handshape reads the same on a hand with fewer fingers. Curl of a long finger is the sum of its
three joints' flexion, i.e. the axis-angle component about the flexion axis (−z for the left
hand, +z for the right: with flat palms down in the T-pose, fingers curl towards −y).

The thumb moves along SMPL-X's relaxed-hand path (thumb1-3 of the hands mean): its position on
that path, t = Σ θ_i·m_i / Σ |m_i|² (0 straight, 1 relaxed, ≈1.6 across the palm in a fist,
< 0 spread out, as in a Y), carries both its opposition and its flexion. A summed rotation
magnitude (the old curl) saturated for any relaxed hand; this does not:
opposition = clip(t / `FULL_OPPOSITION`), flexion = clip(t / `FULL_THUMB`), so a relaxed thumb
sits mid-range. On Dex3 the flexion joints (thumb_1, thumb_2) bring the thumb to the fingers,
and `thumb_0` chooses which finger it meets; opposition turns it towards the index (the
pinch, up to `OPPOSE_RANGE` of its range; the direction is found from the hand's own landmarks:
the side that brings the half-closed thumb's tip nearer the index fingertip).

| robot finger (Dex3) | robot joints (base → tip)            | human source                              |
|---------------------|--------------------------------------|-------------------------------------------|
| thumb               | thumb_0 ← opposition, thumb_1, thumb_2 ← flexion | thumb1-3 along the relaxed path |
| index               | index_0 ← MCP, index_1 ← PIP+DIP     | index1 ; index2+index3                    |
| middle              | middle_0 ← MCP, middle_1 ← PIP+DIP   | mean of middle, ring and pinky (merged: Dex3 has three fingers) |

A flexion joint's value is `curl × closed`, with `closed` its limit farther from zero (the
closing direction on both Dex3 hands), so outputs are always within the limits.

A palm laid on the body (`fold_thumbs`): a flat human thumb lies alongside the palm, but the
Dex3 thumb at zero flexion stands ~9.7 cm out of the palm face (thumb_0 turns it about an axis
near the palm normal and does not lower it). Fully flexed (thumb_1 at its closed limit) it lies
along the palm, 2.8 cm proud of the palm landmark, the least of any thumb pose (measured on the
collision meshes over a grid of all three joints). So where the human's palm rests against the
body, facing it, with a free (unopposed) thumb, the thumb's flexion is raised towards closed:
otherwise the thumb, not the palm, touches, and the collision margin holds the palm ~4 cm off
(the opposite-shoulder sign). The handshape measure then reads a flexed thumb where the
human's is flat: the price of the palm's contact.
"""

from __future__ import annotations

import numpy as np

from embody.io.hands import hand_mean
from embody.motion import JOINT_NAMES
from embody.retarget.limits import clamp_velocity
from embody.robot import Robot

_OPPOSE: dict[tuple[int, str], float] = {}

#: Human flexion (rad) that counts as fully closed: MCP, PIP+DIP and the whole thumb.
FULL_MCP = 1.5
FULL_DISTAL = 2.6
FULL_THUMB = 2.2
#: Position on the relaxed thumb path that counts as fully opposed (a fist's thumb is ≈1.6).
FULL_OPPOSITION = 1.6
#: Share of thumb_0's range used at full opposition (half: the thumb meets the index tip).
OPPOSE_RANGE = 0.5
_AXIS = {"left": np.array([0.0, 0.0, -1.0]), "right": np.array([0.0, 0.0, 1.0])}


def _joint(side: str, name: str) -> int:
    return JOINT_NAMES.index(f"{side}_{name}")


def thumb_path(pose: np.ndarray, side: str) -> np.ndarray:
    """Position (T,) of the thumb on the SMPL-X relaxed-hand path (0 straight, 1 relaxed)."""
    mean = hand_mean().astype(np.float64)[(0 if side == "left" else 15) + 12:(0 if side == "left" else 15) + 15]
    theta = np.stack([pose[:, _joint(side, f"thumb{i}")] for i in (1, 2, 3)], 1)
    return np.einsum("tia,ia->t", theta, mean) / float((mean**2).sum())


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
    t = thumb_path(pose, side)
    return {"thumb": np.clip(t / FULL_THUMB, 0.0, 1.0),
            "thumb_opposition": np.clip(t / FULL_OPPOSITION, 0.0, 1.0),
            "index_mcp": index[0], "index_distal": index[1],
            "middle_mcp": np.mean([r[0] for r in rest], axis=0),
            "middle_distal": np.mean([r[1] for r in rest], axis=0)}


def _closed(robot: Robot, name: str) -> float:
    j = robot.joint_index(name)
    lo, hi = robot.lower[j], robot.upper[j]
    return float(hi if abs(hi) >= abs(lo) else lo)


def opposition_sign(robot: Robot, side: str, joint: str) -> float:
    """+1 or −1: the direction of `joint` that brings the thumb tip nearer the index fingertip
    (from the robot's landmarks; the closing limit's sign when it has none)."""
    key = (id(robot), joint)
    if key not in _OPPOSE:
        names = [f"{side}_thumb_tip", f"{side}_index_tip"]
        if all(n in robot.spec.landmarks for n in names):
            dist = []
            for sign in (1.0, -1.0):
                q = robot.tpose.copy()
                q[robot.joint_index(joint)] = sign * 0.5
                for jn in robot.hand_joint_names(side):  # thumb half closed, as when opposing
                    if "thumb_0" not in jn and "thumb" in jn:
                        q[robot.joint_index(jn)] = 0.5 * _closed(robot, jn)
                p, _, _ = robot.landmark_points(q[None], names)
                dist.append(np.linalg.norm(p[0, 0] - p[0, 1]))
            _OPPOSE[key] = 1.0 if dist[0] < dist[1] else -1.0
        else:
            _OPPOSE[key] = float(np.sign(_closed(robot, joint)) or 1.0)
    return _OPPOSE[key]


#: A palm within this fraction of `ik.touch_radius` of a landmark is fully laid on it (the
#: thumb fully folded); beyond `touch_radius` the thumb is untouched (smoothstep between).
FOLD_NEAR = 0.7
#: Thumb opposition curls of a free thumb (fully folded at or below the first; a relaxed flat
#: hand's is ≈0.13) and of an opposed one (never folded).
FREE_THUMB = (0.3, 0.7)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def palm_rest_weight(distance: np.ndarray, facing: np.ndarray, opposition: np.ndarray,
                     radius: float) -> np.ndarray:
    """How much a human palm rests on the body (T,): near its nearest landmark (`distance` in
    body scales, full within `FOLD_NEAR`·`radius`, none beyond `radius`), facing it (`facing`: the
    cosine between the palm normal and the palm → landmark direction, none at ≤ 0) and with a
    free thumb (`opposition`, the thumb's opposition curl: full below `FREE_THUMB[0]`, none above
    `FREE_THUMB[1]`; an opposed thumb makes a pinch or a fist and keeps its mapping)."""
    near = _smoothstep((radius - np.asarray(distance)) / max(radius * (1.0 - FOLD_NEAR), 1e-12))
    lo, hi = FREE_THUMB
    free = 1.0 - _smoothstep((np.asarray(opposition) - lo) / (hi - lo))
    return near * _smoothstep(np.asarray(facing) / 0.5) * free


def fold_thumbs(hand_q: np.ndarray, hand_joints: list[str], robot: Robot, weight: np.ndarray) -> np.ndarray:
    """`hand_q` with each thumb's flexion joints (thumb_1, thumb_2) raised towards closed by
    `weight` (T,2) [left, right]: curl → max(curl, weight), so a thumb already flexed further
    keeps its value; opposition (thumb_0) is kept. See the module docstring for why."""
    q = np.array(hand_q, dtype=np.float64, copy=True)
    for k, side in enumerate(("left", "right")):
        for jn in robot.spec.hands.get(side, {}).get("thumb", [])[1:]:
            if jn not in hand_joints:
                continue
            c, closed = hand_joints.index(jn), _closed(robot, jn)
            if closed == 0.0:
                continue
            curl = np.maximum(q[:, c] / closed, weight[:, k])
            j = robot.joint_index(jn)
            q[:, c] = np.clip(curl * closed, robot.lower[j], robot.upper[j])
    return q


def rate_limit(hand_q: np.ndarray, vmax: np.ndarray, fps: float) -> np.ndarray:
    """`hand_q` (T,H) within the hand joints' velocity limits `vmax` (H,): the mean of a forward
    and a backward one-pass clamp (each feasible, so their mean is; symmetric in time, so the
    finger lags neither ahead nor behind). Why: a jittering human hand (fingertips at 1-4 m/s)
    flips the fingers and the folded thumb faster than the robot's finger joints can move; the
    final velocity clamp then rewrites them after the IK has placed the arms around the old
    fingers, and the contact repair untangles what the rewritten thumb now touches (30-80°
    arm changes on synth seq 6). Limiting the targets lets the IK see the fingers it will get."""
    q = np.asarray(hand_q, dtype=np.float64)
    if len(q) < 2 or q.shape[1] == 0:
        return q.copy()
    fwd = clamp_velocity(q, vmax, fps)
    bwd = clamp_velocity(q[::-1], vmax, fps)[::-1]
    return 0.5 * (fwd + bwd)


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
            "thumb": [curls["thumb_opposition"], curls["thumb"], curls["thumb"]],
            "index": [curls["index_mcp"], curls["index_distal"]],
            "middle": [curls["middle_mcp"], curls["middle_distal"]],
        }
        for finger in ("thumb", "index", "middle"):
            for k, (jn, curl) in enumerate(zip(fingers.get(finger, []), sources[finger])):
                j = robot.joint_index(jn)
                if finger == "thumb" and k == 0:  # opposition: towards the fingers, up to the limit
                    sign = opposition_sign(robot, side, jn)
                    value = curl * OPPOSE_RANGE * (robot.upper[j] if sign > 0 else robot.lower[j])
                else:
                    value = curl * _closed(robot, jn)
                columns.append(np.clip(value, robot.lower[j], robot.upper[j]))
                names.append(jn)
    q = np.stack(columns, axis=1) if columns else np.zeros((len(pose), 0))
    return q, names
