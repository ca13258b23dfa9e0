"""Up axis and hand convention read from the motion itself, as a check on what a file's keys claim.

A reader decides the conventions from keys (BEAT2's `model`, AMASS's frame-rate key, embody's
own metadata) or a dataset's documented default; one missing or wrong key then reads a clip
lying on its back or with wrong fingers, silently. The data says it too:

* **Up axis**: SMPL-X's rest body stands along its model +y, so the root rotation applied to +y
  is the body's up in the file's world. Averaged over the clip it points along +y (y-up), +z
  (z-up, AMASS) or −y (the OpenCV camera frame of video fits). A clip whose body is not upright
  on average (lying, tumbling) cannot tell.
* **Hand convention**: "relative" hands are offsets from the SMPL-X hand mean (mannequin-x's
  `hand_mean`, a relaxed curl), "absolute" ones are the pose itself. Each non-thumb finger's curl
  is measured along the mean's own axes under both readings. A reading that bends fingers
  backwards (total curl under −0.5 rad) or past a fist (over 4.7 rad) in more than 5 % of
  samples is refuted (when both are, one with at most a third of the other's such samples
  stands): relative hands read as absolute bend back wherever the hand is flatter than the mean. With neither refuted, a relative reading whose median curl is 1.7× the mean's
  or more (every frame near a fist) points to absolute hands. Nothing else decides: flat-handed
  absolute signing looks like relaxed relative hands, so then the data cannot tell.

Constant-zero roots or hands carry no evidence (fixtures, body-only files) and are not judged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from embody.io.hands import hand_mean
from embody.motion import LEFT_HAND, RIGHT_HAND

#: Body up (+y of the SMPL-X rest pose) in each up-axis convention's world frame.
_UP = {"y": np.array([0.0, 1.0, 0.0]), "z": np.array([0.0, 0.0, 1.0]),
       "camera": np.array([0.0, -1.0, 0.0])}
#: Agreement of the clip's mean body up with an axis that decides it.
UP_DECISIVE = 0.8
#: Anatomical bounds of one finger's total curl (MCP + PIP + DIP flexion, rad).
CURL_MIN, CURL_MAX = -0.5, 4.7
#: Share of finger samples out of those bounds that refutes a reading.
REFUTED_SHARE = 0.05
#: Median curl (in units of the mean's) of the relative reading that points to absolute hands.
DOUBLE_CURL = 1.7
#: Non-thumb joints of one hand in SMPL-X order: index, middle, pinky, ring (3 each).
_FINGERS = np.arange(12).reshape(4, 3)


@dataclass(frozen=True)
class Finding:
    """What the data says about one convention: a value, or None when it cannot tell, and why."""

    value: str | None
    detail: str


def detect_up_axis(root_rotvec: np.ndarray) -> Finding | None:
    """The up axis the body's rest orientation points along (None: no root rotation at all)."""
    root = np.asarray(root_rotvec, dtype=np.float64).reshape(-1, 3)
    if not np.any(np.abs(root) > 1e-8):
        return None
    up = Rotation.from_rotvec(root).apply([0.0, 1.0, 0.0]).mean(axis=0)
    scores = {axis: float(up @ v) for axis, v in _UP.items()}
    best = max(scores, key=scores.__getitem__)
    detail = (f"the body's rest up (pelvis to head) averages {np.round(up, 2).tolist()} "
              f"in the file's frame")
    if scores[best] >= UP_DECISIVE:
        return Finding(best, detail + f": {best}-up")
    return Finding(None, detail + ", along no axis (not upright on average)")


def _curls(hands: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Per frame and finger (T, 8): total curl along the mean's per-joint axes (rad)."""
    axes = mean / np.maximum(np.linalg.norm(mean, axis=-1, keepdims=True), 1e-9)
    flex = np.einsum("tjc,jc->tj", hands, axes)  # (T, 30): left 15, right 15
    return np.concatenate([flex[:, _FINGERS].sum(-1), flex[:, 15 + _FINGERS].sum(-1)], axis=1)


def detect_hands(pose: np.ndarray) -> Finding | None:
    """The hand convention the finger flexion fits (None: constant-zero hands, no evidence)."""
    pose = np.asarray(pose, dtype=np.float64)
    hands = np.concatenate([pose[:, LEFT_HAND], pose[:, RIGHT_HAND]], axis=1)  # (T, 30, 3)
    if not np.any(np.abs(hands) > 1e-8):
        return None
    mean = hand_mean().astype(np.float64)
    relaxed = _curls(mean[None], mean)[0]  # the mean's own curl per finger
    readings = {"absolute": _curls(hands, mean), "relative": _curls(hands + mean, mean)}
    bad = {k: float(np.mean((c < CURL_MIN) | (c > CURL_MAX))) for k, c in readings.items()}
    median = {k: float(np.median(c / relaxed)) for k, c in readings.items()}
    detail = ("finger curl as a share of the relaxed hand mean's: median "
              + ", ".join(f"{median[k]:.2f} read {k}" for k in readings)
              + "; out of anatomical range: "
              + ", ".join(f"{100 * bad[k]:.0f}% read {k}" for k in readings))
    refuted = [k for k in readings if bad[k] > REFUTED_SHARE]
    if len(refuted) == 1:
        return Finding(next(k for k in readings if k not in refuted), detail)
    if refuted:  # both: a reading with a third of the other's impossible samples still stands
        low, high = sorted(readings, key=bad.__getitem__)
        return Finding(low if 3 * bad[low] <= bad[high] else None, detail)
    if not refuted and median["relative"] >= DOUBLE_CURL:
        return Finding("absolute", detail)
    return Finding(None, detail)
