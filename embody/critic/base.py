"""The critic protocol: look at reference vs robot, answer with an `Action`."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from embody.critic.action import Action, Limits


@dataclass
class CritiqueContext:
    """What a critic may look at in one round.

    Positions are (T,2,3) and rotations (T,2,3,3) [left, right] in the robot torso frame. The
    reference is the human motion's targets (never the offset working targets), so the critic
    judges the robot against what the signer did.
    """

    round: int
    fps: float
    arm_length: float
    reference_pos: np.ndarray
    reference_rot: np.ndarray
    robot_pos: np.ndarray
    robot_rot: np.ndarray
    limits: Limits
    #: PNG bytes: the comparison sheet and the keyframe pairs (only for critics that need images).
    sheet_png: bytes | None = None
    keyframe_pngs: list[bytes] = field(default_factory=list)
    keyframes: list[int] = field(default_factory=list)
    text: str = ""
    #: The human as reference (when the body and the robot's landmarks are known): per frame and
    #: hand (T,2,3) how far the robot palm must move, torso frame (m), to sit where the human's
    #: is relative to the nearest face/body landmark (0 where the human hand is near none), and
    #: this round's fidelity aggregates (`location_err` in body scales, `palm_deg`).
    location_offset: np.ndarray | None = None
    fidelity: dict[str, float] = field(default_factory=dict)
    #: Robot body scale (m): location thresholds are in body scales.
    body_scale: float = 0.0
    #: Per hand ("left", "right"): `landmark` (the human palm's most frequent nearest landmark),
    #: `share` of frames it is nearest, `location_err` (body scales) and `location_cm` (robot cm)
    #: of the palm's offset from it, `palm_deg` (palm-normal angle error), `yaw_deg` (the turn
    #: about torso z toward the human's palm and pointing direction): the numbers a VLM critic
    #: reads next to the images.
    hand_fidelity: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: (T,2) frames where the robot hand stands at its clearance from the face or chest, so the
    #: part of `location_offset` toward that surface was dropped (`embody.critic.reach`).
    reach_blocked: np.ndarray | None = None
    #: Filled by the critic: request/response record for this round (JSON-able).
    record: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.reference_pos.shape[0])


class Critic(ABC):
    """Turns one round's context into an action."""

    #: Whether `critique` looks at renders; the loop renders only for critics that do.
    needs_images: bool = False

    @abstractmethod
    def critique(self, context: CritiqueContext) -> Action:
        """Return the action for this round; invalid replies come back as `Action.rejected`."""
