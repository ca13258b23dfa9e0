"""Control primitives: small named corrections of the wrist targets, in the robot torso frame.

A critic (geometric or VLM) speaks in these primitives; the loop applies them as offsets to the
IK *targets* and re-solves, while the reference (the human motion) stays fixed.

Names (torso frame: x forward, y left, z up; "in" means toward the body midline):

* position, metres (default `critic.position_step_m`, 10 cm)::

    move_{left,right}_{up,down,forward,back,in,out}

  up/down = ±z, forward/back = ±x, in = −y for the left hand and +y for the right hand.

* orientation, degrees (default `critic.angle_step_deg`, 20°), a rotation of the wrist target
  about a torso axis, applied on the left (R' = R_axis(θ) · R)::

    {left,right}_yaw_{in,out}     about z: "in" turns the hand's forward axis toward the midline
    {left,right}_pitch_{up,down}  about y: "up" tilts the hand's forward axis up
    {left,right}_roll_{in,out}    about x: "in" tilts the top of the hand toward the midline

Each item is a string (``"move_left_up"``: default amount, whole sequence) or an object
``{"name": "move_left_up", "amount": 0.05, "window": [start, end]}`` where `amount` (> 0,
metres or degrees) and `window` (inclusive frame indices) may be null. A windowed offset is full
inside the window and ramps in/out smoothly over `critic.blend_s` outside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

Side = Literal["left", "right"]
SIDES: tuple[Side, ...] = ("left", "right")

_POSITION_DIRS = ("up", "down", "forward", "back", "in", "out")
ORIENTATION_DIRS = {"yaw": ("in", "out"), "pitch": ("up", "down"), "roll": ("in", "out")}

POSITION_NAMES: tuple[str, ...] = tuple(
    f"move_{side}_{d}" for side in SIDES for d in _POSITION_DIRS)
ORIENTATION_NAMES: tuple[str, ...] = tuple(
    f"{side}_{axis}_{d}" for side in SIDES for axis, dirs in ORIENTATION_DIRS.items()
    for d in dirs)


def position_direction(side: Side, direction: str) -> np.ndarray:
    """Unit vector of a position primitive in the torso frame."""
    inward = -1.0 if side == "left" else 1.0  # the left hand sits at +y
    return np.array({
        "up": (0, 0, 1), "down": (0, 0, -1), "forward": (1, 0, 0), "back": (-1, 0, 0),
        "in": (0, inward, 0), "out": (0, -inward, 0),
    }[direction], dtype=np.float64)


def rotation_axis(side: Side, axis: str, direction: str) -> np.ndarray:
    """Signed unit axis of an orientation primitive: a positive angle about it does the named turn."""
    inward = -1.0 if side == "left" else 1.0
    if axis == "yaw":  # Rz(+θ) turns +x toward +y
        sign = inward if direction == "in" else -inward
        return np.array([0.0, 0.0, sign])
    if axis == "pitch":  # Ry(+θ) turns +x toward −z
        return np.array([0.0, -1.0 if direction == "up" else 1.0, 0.0])
    # roll: Rx(+θ) turns +z toward −y
    sign = -inward if direction == "in" else inward
    return np.array([sign, 0.0, 0.0])


def axis_angle_matrix(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: rotations (..., 3, 3) about a fixed unit axis by angles (...) in radians."""
    angle = np.asarray(angle, dtype=np.float64)[..., None, None]
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class Primitive:
    """One parsed primitive with its amount resolved (metres or degrees, > 0)."""

    name: str
    amount: float
    window: tuple[int, int] | None = None

    @property
    def kind(self) -> Literal["position", "orientation"]:
        return "position" if self.name.startswith("move_") else "orientation"

    @property
    def side(self) -> Side:
        parts = self.name.split("_")
        return parts[1] if self.kind == "position" else parts[0]  # type: ignore[return-value]

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "amount": self.amount,
                "window": list(self.window) if self.window is not None else None}


def window_weights(num_frames: int, window: tuple[int, int] | None, blend_frames: int) -> np.ndarray:
    """Per-frame weight in [0,1]: 1 inside the window, a cosine ramp over `blend_frames` outside."""
    if window is None:
        return np.ones(num_frames)
    start, end = window
    t = np.arange(num_frames, dtype=np.float64)
    dist = np.maximum(np.maximum(start - t, t - end), 0.0)  # frames outside the window
    if blend_frames <= 0:
        return (dist == 0).astype(np.float64)
    x = np.clip(dist / (blend_frames + 1), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


def apply_primitives(wrist_pos: np.ndarray, wrist_rot: np.ndarray,
                     primitives: tuple[Primitive, ...] | list[Primitive],
                     blend_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """New wrist targets (T,2,3) and (T,2,3,3) [left, right] with every primitive applied."""
    pos = np.array(wrist_pos, dtype=np.float64)
    rot = np.array(wrist_rot, dtype=np.float64)
    num_frames = pos.shape[0]
    for prim in primitives:
        s = SIDES.index(prim.side)
        w = window_weights(num_frames, prim.window, blend_frames)
        if prim.kind == "position":
            direction = prim.name.split("_")[2]
            pos[:, s] += w[:, None] * prim.amount * position_direction(prim.side, direction)
        else:
            _, axis, direction = prim.name.split("_")
            r = axis_angle_matrix(rotation_axis(prim.side, axis, direction),
                                  w * np.radians(prim.amount))
            rot[:, s] = r @ rot[:, s]
    return pos, rot
