"""Handshapes as absolute SMPL-X finger poses (15,3), written for the left hand and mirrored.

Left hand at rest: fingers along +x, palm facing -y, so finger flexion is a rotation about -z
and spreading is about y. The right hand mirrors through the x=0 plane: (x, y, z) → (x, -y, -z).
Finger order (SMPL-X): index, middle, pinky, ring, thumb; three joints each.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from embody.io.hands import hand_mean

FINGERS = ("index", "middle", "pinky", "ring")
MIRROR = np.array([1.0, -1.0, -1.0])
#: spread direction of each finger about +y for the left hand, whose thumb side is +z: a
#: positive angle turns a finger toward -z (the pinky), so the index spreads negative.
_SPREAD_SIGN = {"index": -1.0, "middle": -0.2, "ring": 0.6, "pinky": 1.0}


def _finger(flex: tuple[float, float, float], spread: float = 0.0) -> np.ndarray:
    out = np.zeros((3, 3))
    out[:, 2] = -np.asarray(flex)
    out[0, 1] = spread
    return out


def _thumb(curl: float) -> np.ndarray:
    """Thumb along the relaxed mean's path: 0 is straight, 1 relaxed, ~2 across the palm."""
    return curl * hand_mean()[12:15].astype(np.float64)


def _shape(fingers: dict[str, tuple[float, float, float]], thumb: float, spread: float = 0.0) -> np.ndarray:
    parts = [_finger(fingers[f], spread * _SPREAD_SIGN[f]) for f in FINGERS]
    return np.concatenate(parts + [_thumb(thumb)])


STRAIGHT = (0.0, 0.0, 0.0)
CURLED = (1.45, 1.55, 0.95)
BENT = (0.75, 0.85, 0.55)
HOOK = (0.1, 1.3, 1.0)


@lru_cache(maxsize=None)
def _library() -> dict[str, np.ndarray]:
    all_ = lambda f: {k: f for k in FINGERS}  # noqa: E731
    lib = {
        "flat": _shape(all_(STRAIGHT), thumb=0.2),
        "spread": _shape(all_(STRAIGHT), thumb=0.0, spread=0.35),
        "fist": _shape(all_(CURLED), thumb=1.6),
        "point": _shape({**all_(CURLED), "index": STRAIGHT}, thumb=1.6),
        "v": _shape({**all_(CURLED), "index": STRAIGHT, "middle": STRAIGHT}, thumb=1.6, spread=0.3),
        "pinch": _shape({**all_(STRAIGHT), "index": BENT}, thumb=1.3, spread=0.15),
        "c": _shape(all_(BENT), thumb=0.9),
        "claw": _shape(all_(HOOK), thumb=0.8, spread=0.3),
        "y": _shape({**all_(CURLED), "pinky": STRAIGHT}, thumb=-0.2, spread=0.3),
        "relaxed": hand_mean()[:15].astype(np.float64),
    }
    for pose in lib.values():
        pose.setflags(write=False)
    return lib


HANDSHAPES = ("flat", "spread", "fist", "point", "v", "pinch", "c", "claw", "y", "relaxed")


def handshape(name: str, side: str) -> np.ndarray:
    """Absolute finger pose (15,3) of handshape `name` for side 'left' or 'right'."""
    pose = _library()[name].copy()
    return pose if side == "left" else pose * MIRROR


def finger_overlap(side: str, severity: float) -> np.ndarray:
    """An impossible hand: index and middle crossed through each other, fingers curled through
    the palm — the finger-overlap artifact of SLG decoders. `severity` in [0, 1]."""
    curl = 1.6 + 0.6 * severity
    fingers = {f: (curl, curl + 0.2, 1.2 + 0.4 * severity) for f in FINGERS}
    pose = _shape(fingers, thumb=2.2 + 0.6 * severity)
    pose[0, 1] += 0.8 + 0.5 * severity   # index swings toward the pinky side...
    pose[3, 1] -= 0.8 + 0.5 * severity   # ...and middle toward the thumb side: they cross
    return pose if side == "left" else pose * MIRROR
