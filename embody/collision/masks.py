"""Which joints the optimisation may move (the mask M of Eq. 2)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from embody.errors import ConfigError
from embody.motion import JOINT_NAMES, NUM_JOINTS

_HANDS = JOINT_NAMES[25:55]
_WRISTS = ("left_wrist", "right_wrist")
_ARMS = ("left_collar", "right_collar", "left_shoulder", "right_shoulder",
         "left_elbow", "right_elbow")
_TRUNK = ("spine1", "spine2", "spine3", "neck", "head")

#: Presets: `hands` is the paper's setting (the 30 finger joints).
PRESETS: dict[str, tuple[str, ...]] = {
    "hands": _HANDS,
    "hands_wrists": _WRISTS + _HANDS,
    "arms": _ARMS + _WRISTS + _HANDS,
    "upper_body": _TRUNK + _ARMS + _WRISTS + _HANDS,
}


def mask_joints(preset: str, joints: Sequence[str] = ()) -> np.ndarray:
    """Sorted SMPL-X joint indices that may move; `preset="joints"` takes the explicit list."""
    if preset == "joints":
        names = tuple(joints)
        if not names:
            raise ConfigError("collision.joints", "mask 'joints' needs at least one joint name")
    elif preset in PRESETS:
        names = PRESETS[preset]
    else:
        raise ConfigError("collision.mask", f"unknown preset {preset!r}; known: "
                          f"{', '.join([*PRESETS, 'joints'])}")
    unknown = [n for n in names if n not in JOINT_NAMES]
    if unknown:
        raise ConfigError("collision.joints", f"unknown joint(s) {unknown}; names are SMPL-X "
                          "joint names as in embody.motion.JOINT_NAMES")
    return np.array(sorted({JOINT_NAMES.index(n) for n in names}), dtype=np.int64)


def mask_vector(preset: str, joints: Sequence[str] = ()) -> np.ndarray:
    """M as a (55,) 0/1 vector."""
    m = np.zeros(NUM_JOINTS, dtype=np.float32)
    m[mask_joints(preset, joints)] = 1.0
    return m
