"""Generator artifacts, injected the way SLG decoders produce them.

Penetrations (hand–torso, hand–face, hand–hand) are placed as wrist targets *inside* the body
before IK, so the skinned mesh really interpenetrates; finger overlap and jitter act on the
finished pose sequence. Every injection returns the record stored in the file's metadata.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from embody.motion import LEFT_HAND, RIGHT_HAND
from embody.synth import space
from embody.synth.handshapes import finger_overlap

PENETRATIONS = ("hand_torso", "hand_face", "hand_hand")
#: arm joints (collars to wrists) and both hands: where decoder jitter shows.
JITTER_JOINTS = np.r_[13, 14, 16:22, 25:55]
#: proximal joints move the whole hand: less noise there keeps wrists within a few cm.
JITTER_SCALE = np.where(JITTER_JOINTS < 18, 0.4, 1.0)


def torso_target(rng: np.random.Generator) -> tuple[np.ndarray, dict[str, Any]]:
    """A dominant-wrist target a few cm behind the torso's front surface."""
    depth = float(rng.uniform(0.02, 0.06))
    target = np.array([rng.uniform(*space.TORSO_X), rng.uniform(*space.TORSO_Y),
                       space.TORSO_FRONT_Z - depth])
    return target, {"hand": "right", "wrist_depth_m": round(depth, 4)}


def face_target(rng: np.random.Generator) -> tuple[np.ndarray, dict[str, Any]]:
    """A dominant-wrist target a few cm inside the face."""
    depth = float(rng.uniform(0.02, 0.05))
    target = np.array([rng.uniform(*space.FACE_X), rng.uniform(*space.FACE_Y),
                       space.FACE_FRONT_Z - depth])
    return target, {"hand": "right", "wrist_depth_m": round(depth, 4)}


def hand_hand_targets(rng: np.random.Generator) -> tuple[np.ndarray, dict[str, Any]]:
    """Left and right wrist targets (2,3) closer than a hand is thick, or crossed."""
    gap = float(rng.uniform(-0.02, 0.03))
    center = np.array([rng.uniform(-0.05, 0.03), rng.uniform(-0.12, 0.05), rng.uniform(0.28, 0.36)])
    half = np.array([gap / 2, 0.0, 0.0])
    return np.stack([center + half, center - half]), {"hand": "both", "gap_m": round(gap, 4)}


def _window(rng: np.random.Generator, frames: int, lo: int, hi: int) -> tuple[int, int]:
    length = int(rng.integers(lo, hi + 1))
    start = int(rng.integers(0, max(frames - length, 1)))
    return start, min(start + length, frames)


def inject_finger_overlap(pose: np.ndarray, rng: np.random.Generator) -> dict[str, Any]:
    """Curl one hand's fingers through each other and the palm for a window (3-frame ramps)."""
    start, end = _window(rng, pose.shape[0], 10, 30)
    side = "left" if rng.random() < 0.5 else "right"
    severity = float(rng.uniform(0.3, 1.0))
    hand = LEFT_HAND if side == "left" else RIGHT_HAND
    target = finger_overlap(side, severity)
    ramp = np.minimum(1.0, np.minimum(np.arange(1, end - start + 1), np.arange(end - start, 0, -1)) / 3.0)
    pose[start:end, hand] += ramp[:, None, None] * (target - pose[start:end, hand])
    return {"kind": "finger_overlap", "start": start, "end": end, "hand": side,
            "severity": round(severity, 3)}


def inject_jitter(pose: np.ndarray, rng: np.random.Generator) -> dict[str, Any]:
    """White noise on arm and hand joint angles: the frame-to-frame flicker of decoders."""
    start, end = _window(rng, pose.shape[0], 15, 45)
    sigma = float(rng.uniform(0.02, 0.06))
    noise = rng.normal(0.0, sigma, size=(end - start, len(JITTER_JOINTS), 3)) * JITTER_SCALE[:, None]
    pose[start:end, JITTER_JOINTS] += noise
    return {"kind": "jitter", "start": start, "end": end, "hand": "both", "sigma_rad": round(sigma, 4)}
