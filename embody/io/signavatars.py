"""SignAvatars pkl: `data['smplx']` (T,182) with mean-relative hands, camera frame.

Layout: root 0:3 | body 3:66 | lhand 66:111 | rhand 111:156 | jaw 156:159 | shape 159:169 |
expr 169:179 | cam_trans 179:182. Like other video fits it is camera-frame (y down), so it gets
the same 180° x rotation as SOKE.

Frame rate: the pickle records none (unless it carries an `fps` key). SignAvatars is 24 fps as its
README states (ZhengdiYu/SignAvatars; the field notes checked on 2026-11-21; the copy of the
README in the public index predates the dataset release and has no data section).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embody.io.conventions import Overrides, Setting, normalise
from embody.io.fields import field, scalar
from embody.motion import NUM_JOINTS, Motion, MotionSource

WIDTH = 182
#: (slice in the 182 layout, first index in the SMPL-X 165 layout)
POSE_PARTS = ((slice(0, 66), 0), (slice(156, 159), 66), (slice(66, 156), 75))
DEFAULT_FPS = Setting(24.0, "default: SignAvatars is 24 fps (its README)")


def is_signavatars(data: Any) -> bool:
    return isinstance(data, dict) and "smplx" in data


def read(path: Path, data: dict[str, Any], overrides: Overrides | None = None) -> Motion:
    raw = field(data, "smplx", path, width=WIDTH)
    poses = np.zeros((raw.shape[0], 165))
    for src, start in POSE_PARTS:
        poses[:, start:start + src.stop - src.start] = raw[:, src]
    fps = (Setting(scalar(data, ("fps",), path, 0.0), "data: fps") if "fps" in data
           else DEFAULT_FPS)
    pose, transl, fps_value, hands, provenance = normalise(
        poses.reshape(-1, NUM_JOINTS, 3), raw[:, 179:182], fps=fps,
        up_axis=Setting("camera", "default: SignAvatars fits are in the camera frame (y down)"),
        hands=Setting("relative", "default: SignAvatars stores mean-relative hands"),
        overrides=overrides)
    return Motion(pose=pose, transl=transl, betas=raw[:, 159:169].mean(axis=0), fps=fps_value,
                  source=MotionSource(str(path), "signavatars", hands, provenance))  # type: ignore[arg-type]
