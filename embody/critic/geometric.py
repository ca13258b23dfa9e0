"""The offline default critic: measures the offsets a VLM would describe, deterministically.

It judges against the human. When the loop gives it the landmark-relative location offsets
(`CritiqueContext.location_offset`: where the robot palm must move so that it sits relative to
the robot's chin, cheek, sternum ... as the human's palm sits relative to the human's), it uses
those (less what the robot's clearances forbid, `embody.critic.reach`), judged in body scales
(`critic.accept_location`), and accepts only when every hand's location error and
palm-orientation error (`critic.accept_palm_deg`) are under their thresholds. Without them (no
body or robot landmarks) it falls back to the reference wrists (IK targets), judged in arm
lengths, and the yaw to the reference (`critic.accept_yaw_deg`). Either way, per side it takes
the offset over the whole sequence or over the worst window when one window is clearly worse,
and answers every threshold it finds exceeded with the primitives that cancel it: position moves
for the location, and for the palm the turn (yaw, pitch, roll) that best brings the robot's
palm onto the human's; amounts quantised like a human critic would speak, never quantised away.
"""

from __future__ import annotations

import numpy as np

from embody.config.critic import CriticConfig
from embody.critic.action import Action
from embody.critic.base import Critic, CritiqueContext
from embody.critic.primitives import ORIENTATION_DIRS, SIDES, Primitive, rotation_axis

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


def _turn_primitives(side: str, turn_deg: np.ndarray, cfg: CriticConfig) -> list[Primitive]:
    """Orientation primitives for a rotation vector (torso x roll, y pitch, z yaw; degrees):
    one per axis whose amount quantises to at least one step, and when none does, one
    quantum about the largest axis, so a rejected palm always gets a turn."""
    prims = []
    for k, axis in ((2, "yaw"), (1, "pitch"), (0, "roll")):
        value = float(turn_deg[k])
        amount = min(_quantise(abs(value), cfg.angle_quantum_deg), cfg.max_angle_deg)
        if amount > 0:
            prims.append(Primitive(_orientation_name(side, axis, value), amount))
    if not prims:
        k = int(np.argmax(np.abs(turn_deg)))
        axis = ("roll", "pitch", "yaw")[k]
        prims.append(Primitive(_orientation_name(side, axis, float(turn_deg[k])),
                               min(cfg.angle_quantum_deg, cfg.max_angle_deg)))
    return prims


def _orientation_name(side: str, axis: str, value: float) -> str:
    """The primitive that turns by a positive `value` (deg) about torso axis `axis`, or a
    negative one the other way (`primitives.rotation_axis` gives each name's signed axis)."""
    k = {"roll": 0, "pitch": 1, "yaw": 2}[axis]
    for direction in ORIENTATION_DIRS[axis]:
        if rotation_axis(side, axis, direction)[k] * value > 0:  # type: ignore[arg-type]
            return f"{side}_{axis}_{direction}"
    return f"{side}_{axis}_{ORIENTATION_DIRS[axis][0]}"


class GeometricCritic(Critic):
    """Deterministic critic over wrist trajectories; needs no renders.

    Every rejection names what is off and carries the primitive that addresses it: a hand whose
    location is over its threshold gets at least one position primitive, a hand whose palm is
    over `accept_palm_deg` (or, without the human, whose yaw is over `accept_yaw_deg`) at least
    one turn. So the verdict is "revise" exactly when there are primitives.
    """

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
            side_palm = float(hand.get("palm_deg", palm_all))
            notes.append(f"{side}: offset {ratio:.3f} {'body scales from the landmark' if human else 'arm lengths'}"
                         + (f" in frames {window[0]}-{window[1]}" if window else "")
                         + (f" ({held} frames at the face/chest clearance)" if held else "")
                         + (f", palm {side_palm:.1f} deg" if human else "")
                         + f", yaw {yaw:+.1f} deg")
            if ratio >= threshold:
                moves = []
                for axis, (positive, negative) in enumerate(_AXES):
                    # y: "in" is −y for the left hand, +y for the right
                    value = dominant[axis] * (-1.0 if (axis == 1 and side == "left") else 1.0)
                    amount = min(_quantise(abs(value), cfg.position_quantum_m), cfg.max_position_m)
                    if amount > 0:
                        moves.append(Primitive(f"move_{side}_{positive if value > 0 else negative}",
                                               amount, window))
                if not moves:  # over the threshold yet under half a quantum per axis
                    axis = int(np.argmax(np.abs(dominant)))
                    value = dominant[axis] * (-1.0 if (axis == 1 and side == "left") else 1.0)
                    positive, negative = _AXES[axis]
                    moves.append(Primitive(f"move_{side}_{positive if value > 0 else negative}",
                                           min(cfg.position_quantum_m, cfg.max_position_m), window))
                prims += moves
            if human:
                # against the human, orientation is judged by the palm normal, and the turn is
                # the rotation toward the human's palm and pointing direction, asked for exactly
                # where the palm is over its threshold: turns that cancelled the IK target's yaw
                # took H1 seq_010's palm error 20.9 → 23.7 → 27.7 deg (default run)
                if side_palm >= cfg.accept_palm_deg:
                    turn = (np.asarray(hand["turn_deg"], np.float64) if "turn_deg" in hand
                            else np.array([0.0, 0.0, yaw]))
                    prims += _turn_primitives(side, turn, cfg)
            elif abs(yaw) >= cfg.accept_yaw_deg:
                prims += _turn_primitives(side, np.array([0.0, 0.0, yaw]), cfg)
        if human:
            notes.append(f"location error {context.fidelity.get('location_err', float('nan')):.3f} "
                         f"body scales, palm {palm_all:.1f} deg")
        verdict = "revise" if prims else "accept"
        return Action(tuple(prims), verdict, "; ".join(notes))
