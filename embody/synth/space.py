"""Signing space: wrist targets around the torso and face of the rest body (y-up, metres,
body facing +z, its left at +x), and the body surfaces artifacts push the hands through.

Numbers were read off mannequin-x's neutral wooden mesh: torso front z ≈ 0.13 for
y ∈ [-0.25, 0.05], face front z ≈ 0.11 for y ∈ [0.22, 0.34].
"""

from __future__ import annotations

import numpy as np

#: Wrist targets for the dominant (right) hand; the left hand uses x → -x.
LOCATIONS: dict[str, tuple[float, float, float]] = {
    "neutral": (-0.15, -0.12, 0.33),
    "neutral_high": (-0.15, 0.05, 0.36),
    "neutral_low": (-0.18, -0.25, 0.30),
    "center": (-0.06, -0.08, 0.36),
    "side": (-0.32, -0.05, 0.25),
    "chest": (-0.08, 0.00, 0.26),
    "chin": (-0.05, 0.14, 0.28),
    "forehead": (-0.08, 0.32, 0.30),
    "cheek": (-0.17, 0.24, 0.24),
    # the palm on the left shoulder's top, 3-5 cm from its landmark (the old (0.10, 0.05, 0.26)
    # held it 27 cm out, nearer the chin than the shoulder)
    "opposite_shoulder": (0.14, 0.19, 0.06),
}
#: Upper-arm posture (shoulder axis-angle) the arm IK starts from and is pulled toward at a place,
#: where the default elbow-down posture does not fit: reaching across to the opposite shoulder
#: with the elbow down drives the forearm ~7 cm into the chest; lifted forward it clears it.
SHOULDER_PRIORS: dict[str, tuple[float, float, float]] = {
    "opposite_shoulder": (0.6, -0.2, 0.3),
}
#: Dominant wrist turn (local axis-angle) at a place the palm lies on, and the share of the
#: random turn (±0.5 rad per axis) kept around it: a full random turn drives the fingers ~3 cm
#: into the shoulder.
WRIST_TURNS: dict[str, tuple[tuple[float, float, float], float]] = {
    "opposite_shoulder": ((-0.8, 0.0, 0.0), 0.3),  # palm down onto the shoulder, thumb clear
}
#: Where a hand waits when it is not signing.
REST = (-0.20, -0.32, 0.18)

TORSO_FRONT_Z = 0.13
TORSO_Y = (-0.22, 0.04)
TORSO_X = (-0.10, 0.10)
FACE_FRONT_Z = 0.11
FACE_Y = (0.22, 0.32)
FACE_X = (-0.04, 0.04)


def location(name: str, side: str) -> np.ndarray:
    x, y, z = REST if name == "rest" else LOCATIONS[name]
    return np.array([x if side == "right" else -x, y, z])
