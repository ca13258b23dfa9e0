"""Hand-pose conventions: SMPL-X "relative" hands are offsets from a relaxed mean pose.

SOKE, SignAvatars and SHOW store relative hands (`flat_hand_mean=False`); AMASS and embody store
absolute hands, where zero is a flat hand. The mean comes from mannequin-x's calibration asset,
so no licensed SMPL-X file is needed.
"""

from __future__ import annotations

from functools import lru_cache
from importlib.resources import files

import numpy as np

from embody.motion import LEFT_HAND, RIGHT_HAND

HANDS = slice(LEFT_HAND.start, RIGHT_HAND.stop)


@lru_cache(maxsize=1)
def _hand_mean() -> np.ndarray:
    resource = files("mannequin") / "assets" / "smplx_calibration.npz"
    with resource.open("rb") as fh, np.load(fh, allow_pickle=False) as data:
        mean = np.asarray(data["hand_mean"], dtype=np.float32)
    mean.setflags(write=False)
    return mean


def hand_mean() -> np.ndarray:
    """SMPL-X relaxed hand mean (30,3) axis-angle: left 15 joints, then right 15."""
    return _hand_mean().copy()


def relative_to_absolute(pose: np.ndarray) -> np.ndarray:
    """Full pose (...,55,3) with mean-relative hands → absolute hands (as smplx adds the mean)."""
    out = np.array(pose, dtype=np.float32)
    out[..., HANDS, :] += _hand_mean()
    return out


def absolute_to_relative(pose: np.ndarray) -> np.ndarray:
    """Inverse of `relative_to_absolute`, for exporting to relative-hand consumers."""
    out = np.array(pose, dtype=np.float32)
    out[..., HANDS, :] -= _hand_mean()
    return out
