"""The offline default critic: measures the wrist offsets a VLM would describe, deterministically.

Per side it takes the reference-minus-robot wrist offset in the torso frame (judged relative to
arm length, so thresholds transfer across robots), over the whole sequence or over the worst
window when one window is clearly worse, plus the mean yaw offset. It answers with the position
and yaw primitives that cancel them, amounts quantised like a human critic would speak.
"""

from __future__ import annotations

import numpy as np

from embody.config.critic import CriticConfig
from embody.critic.action import Action
from embody.critic.base import Critic, CritiqueContext
from embody.critic.primitives import SIDES, Primitive

_AXES = (("forward", "back"), ("in", "out"), ("up", "down"))  # torso x, y (left side), z


def _quantise(value: float, quantum: float) -> float:
    return float(np.round(value / quantum) * quantum)


def worst_window(offset: np.ndarray, length: int) -> tuple[int, np.ndarray]:
    """Start frame and mean offset of the `length`-frame window with the largest mean offset."""
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(offset, axis=0)])
    means = (csum[length:] - csum[:-length]) / length
    start = int(np.argmax(np.linalg.norm(means, axis=1)))
    return start, means[start]


def mean_yaw_deg(reference_rot: np.ndarray, robot_rot: np.ndarray) -> float:
    """Circular mean of the yaw (about torso z) of R_ref · R_robotᵀ, in degrees."""
    rel = reference_rot @ np.swapaxes(robot_rot, -1, -2)
    yaw = np.arctan2(rel[:, 1, 0], rel[:, 0, 0])
    return float(np.degrees(np.arctan2(np.sin(yaw).mean(), np.cos(yaw).mean())))


class GeometricCritic(Critic):
    """Deterministic critic over wrist trajectories; needs no renders."""

    needs_images = False

    def __init__(self, cfg: CriticConfig) -> None:
        self.cfg = cfg

    def critique(self, context: CritiqueContext) -> Action:
        cfg = self.cfg
        num_frames = context.num_frames
        length = int(np.clip(round(cfg.window_s * context.fps), 1, num_frames))
        prims: list[Primitive] = []
        notes: list[str] = []
        for s, side in enumerate(SIDES):
            offset = (np.asarray(context.reference_pos[:, s], np.float64)
                      - np.asarray(context.robot_pos[:, s], np.float64))
            whole = offset.mean(axis=0)
            start, worst = worst_window(offset, length)
            window: tuple[int, int] | None = None
            dominant = whole
            if (length < num_frames
                    and np.linalg.norm(worst) > cfg.window_factor * np.linalg.norm(whole)):
                window, dominant = (start, start + length - 1), worst
            ratio = float(np.linalg.norm(dominant)) / context.arm_length
            yaw = mean_yaw_deg(context.reference_rot[:, s], context.robot_rot[:, s])
            notes.append(f"{side}: offset {ratio:.3f} arm lengths"
                         + (f" in frames {window[0]}-{window[1]}" if window else "")
                         + f", yaw {yaw:+.1f} deg")
            if ratio >= cfg.accept_position:
                for axis, (positive, negative) in enumerate(_AXES):
                    # y: "in" is −y for the left hand, +y for the right
                    value = dominant[axis] * (-1.0 if (axis == 1 and side == "left") else 1.0)
                    amount = min(_quantise(abs(value), cfg.position_quantum_m), cfg.max_position_m)
                    if amount > 0:
                        name = f"move_{side}_{positive if value > 0 else negative}"
                        prims.append(Primitive(name, amount, window))
            if abs(yaw) >= cfg.accept_yaw_deg:
                amount = min(_quantise(abs(yaw), cfg.angle_quantum_deg), cfg.max_angle_deg)
                # a positive yaw about +z turns the hand toward +y: inward for the right hand
                turn_in = (yaw > 0) == (side == "right")
                if amount > 0:
                    prims.append(Primitive(f"{side}_yaw_{'in' if turn_in else 'out'}", amount))
        verdict = "revise" if prims else "accept"
        return Action(tuple(prims), verdict, "; ".join(notes))
