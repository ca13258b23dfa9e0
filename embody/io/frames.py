"""Coordinate-frame fixes applied on load: every motion leaves `embody.io` y-up."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: AMASS is z-up: −90° about x takes +z to +y.
Z_UP_TO_Y_UP = Rotation.from_euler("x", -90, degrees=True).as_matrix()
#: Video fits live in the OpenCV camera frame (y down, z forward): 180° about x makes them y-up.
CAMERA_TO_Y_UP = Rotation.from_euler("x", 180, degrees=True).as_matrix()


def rotate_root(pose: np.ndarray, transl: np.ndarray,
                rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotate a whole motion about the world origin: root orientation and translation.

    Only joint 0 changes in `pose`; every other joint is parent-relative.
    """
    pose = np.array(pose, dtype=np.float64)
    root = Rotation.from_matrix(rotation) * Rotation.from_rotvec(pose[:, 0])
    pose[:, 0] = root.as_rotvec()
    transl = np.asarray(transl, dtype=np.float64) @ np.asarray(rotation).T
    return pose.astype(np.float32), transl.astype(np.float32)
