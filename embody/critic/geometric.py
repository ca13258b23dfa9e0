"""The offline default critic: measures the offsets a VLM would describe, deterministically.

It judges against the human. When the loop gives it the landmark-relative location offsets
(`CritiqueContext.location_offset`: where the robot palm must move so that it sits relative to
the robot's chin, cheek, sternum ... as the human's palm sits relative to the human's), it uses
those (less what the robot's clearances forbid, `embody.critic.reach`), judged in body scales
(`critic.accept_location`), and accepts only when the location error and the palm-orientation
error (`critic.accept_palm_deg`) are under their thresholds; it asks for a yaw turn only for a
hand whose palm error is over its threshold. Without
them (no body or robot landmarks) it falls back to the reference wrists (IK targets), judged in
arm lengths. Either way, per side it takes the offset over the whole sequence or over the worst
window when one window is clearly worse, plus the mean yaw offset, and answers with the position
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
        human = context.location_offset is not None and context.body_scale > 0
        palm_all = context.fidelity.get("palm_deg", 0.0) if human else 0.0
        for s, side in enumerate(SIDES):
            if human:
                offset = np.asarray(context.location_offset[:, s], np.float64)
            else:
                offset = (np.asarray(context.reference_pos[:, s], np.float64)
                          - np.asarray(context.robot_pos[:, s], np.float64))
            whole = offset.mean(axis=0)
            start, worst = worst_window(offset, length)
            window: tuple[int, int] | None = None
            dominant = whole
            if (length < num_frames
                    and np.linalg.norm(worst) > cfg.window_factor * np.linalg.norm(whole)):
                window, dominant = (start, start + length - 1), worst
            scale = context.body_scale if human else context.arm_length
            ratio = float(np.linalg.norm(dominant)) / scale
            threshold = cfg.accept_location if human else cfg.accept_position
            hand = context.hand_fidelity.get(side, {}) if human else {}
            yaw = (float(hand["yaw_deg"]) if "yaw_deg" in hand
                   else mean_yaw_deg(context.reference_rot[:, s], context.robot_rot[:, s]))
            held = (int(np.count_nonzero(context.reach_blocked[:, s]))
                    if human and context.reach_blocked is not None else 0)
            notes.append(f"{side}: offset {ratio:.3f} {'body scales from the landmark' if human else 'arm lengths'}"
                         + (f" in frames {window[0]}-{window[1]}" if window else "")
                         + (f" ({held} frames at the face/chest clearance)" if held else "")
                         + f", yaw {yaw:+.1f} deg")
            if ratio >= threshold:
                for axis, (positive, negative) in enumerate(_AXES):
                    # y: "in" is −y for the left hand, +y for the right
                    value = dominant[axis] * (-1.0 if (axis == 1 and side == "left") else 1.0)
                    amount = min(_quantise(abs(value), cfg.position_quantum_m), cfg.max_position_m)
                    if amount > 0:
                        name = f"move_{side}_{positive if value > 0 else negative}"
                        prims.append(Primitive(name, amount, window))
            # against the human, orientation is judged by the palm normal, and the turn is the
            # yaw toward the human's palm and pointing direction (`hand_fidelity[side]
            # ["yaw_deg"]`), asked for only where the palm is off: turns that cancelled the IK
            # target's yaw took H1 seq_010's palm error 20.9 → 23.7 → 27.7 deg (default run)
            side_palm = float(hand.get("palm_deg", palm_all))
            if abs(yaw) >= cfg.accept_yaw_deg and (not human or side_palm >= cfg.accept_palm_deg):
                amount = min(_quantise(abs(yaw), cfg.angle_quantum_deg), cfg.max_angle_deg)
                # a positive yaw about +z turns the hand toward +y: inward for the right hand
                turn_in = (yaw > 0) == (side == "right")
                if amount > 0:
                    prims.append(Primitive(f"{side}_yaw_{'in' if turn_in else 'out'}", amount))
        palm = palm_all
        if human:
            notes.append(f"location error {context.fidelity.get('location_err', float('nan')):.3f} "
                         f"body scales, palm {palm:.1f} deg")
        verdict = "revise" if prims or palm >= cfg.accept_palm_deg else "accept"
        return Action(tuple(prims), verdict, "; ".join(notes))
