"""SignAvatars pkl: `data['smplx']` (T,182) with mean-relative hands, camera frame.

Layout: root 0:3 | body 3:66 | lhand 66:111 | rhand 111:156 | jaw 156:159 | shape 159:169 |
expr 169:179 | cam_trans 179:182. Like other video fits it is camera-frame (y down), so it gets
the same 180° x rotation as SOKE.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embody.io.fields import field, scalar
from embody.io.frames import CAMERA_TO_Y_UP, rotate_root
from embody.io.hands import relative_to_absolute
from embody.motion import NUM_JOINTS, Motion, MotionSource

WIDTH = 182
#: (slice in the 182 layout, first index in the SMPL-X 165 layout)
POSE_PARTS = ((slice(0, 66), 0), (slice(156, 159), 66), (slice(66, 156), 75))


def is_signavatars(data: Any) -> bool:
    return isinstance(data, dict) and "smplx" in data


def read(path: Path, data: dict[str, Any], fps: float = 30.0) -> Motion:
    raw = field(data, "smplx", path, width=WIDTH)
    poses = np.zeros((raw.shape[0], 165))
    for src, start in POSE_PARTS:
        poses[:, start:start + src.stop - src.start] = raw[:, src]
    pose = relative_to_absolute(poses.reshape(-1, NUM_JOINTS, 3))
    pose, transl = rotate_root(pose, raw[:, 179:182], CAMERA_TO_Y_UP)
    return Motion(pose=pose, transl=transl, betas=raw[:, 159:169].mean(axis=0),
                  fps=scalar(data, ("fps",), path, fps),
                  source=MotionSource(str(path), "signavatars", "relative"))
