"""SOKE (CSL-Daily SMPL-X): one pickle per frame under `poses/<name>/`, split index files.

Frames are in the camera frame with mean-relative hands; we rotate 180° about x (as SignBot)
and add the hand mean. SOKE gives no frame rate; CSL-Daily video is ~30 fps.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError
from embody.io.fields import field, read_pickle
from embody.io.frames import CAMERA_TO_Y_UP, rotate_root
from embody.io.hands import relative_to_absolute
from embody.motion import NUM_JOINTS, Motion, MotionSource

SPLITS = ("train", "val", "test")
#: (key, width, first pose index) in SMPL-X 165 layout; eyes stay zero.
FRAME_FIELDS = (("smplx_root_pose", 3, 0), ("smplx_body_pose", 63, 3), ("smplx_jaw_pose", 3, 66),
                ("smplx_lhand_pose", 45, 75), ("smplx_rhand_pose", 45, 120))


def frame_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.suffix == ".pkl" and p.is_file())


def is_sequence_dir(directory: Path) -> bool:
    return directory.is_dir() and bool(frame_files(directory))


def _frame(path: Path) -> dict[str, Any]:
    data = read_pickle(path)
    if not isinstance(data, dict):
        raise InputError(path, None, f"expected a dict of SMPL-X fields, got {type(data).__name__}")
    return data


def _vector(data: dict[str, Any], key: str, width: int, path: Path) -> np.ndarray:
    arr = field(data, key, path).reshape(-1)
    if arr.shape[0] != width:
        raise InputError(path, key, f"expected {width} values, got {arr.shape[0]}")
    return arr


def read(directory: Path, fps: float = 30.0) -> Motion:
    files = frame_files(directory)
    if not files:
        raise InputError(directory, None, "no per-frame .pkl files (empty SOKE sequence)")
    poses = np.zeros((len(files), 165))
    transl = np.zeros((len(files), 3))
    shapes = np.zeros((len(files), 10))
    for i, path in enumerate(files):
        data = _frame(path)
        for key, width, start in FRAME_FIELDS:
            poses[i, start:start + width] = _vector(data, key, width, path)
        shapes[i] = _vector(data, "smplx_shape", 10, path) if "smplx_shape" in data else 0.0
        transl[i] = _vector(data, "cam_trans", 3, path) if "cam_trans" in data else 0.0
    pose = relative_to_absolute(poses.reshape(-1, NUM_JOINTS, 3))
    pose, transl = rotate_root(pose, transl, CAMERA_TO_Y_UP)
    return Motion(pose=pose, transl=transl, betas=shapes.mean(axis=0), fps=fps,
                  source=MotionSource(str(directory), "soke", "relative"))


def read_split(root: Path, split: str) -> list[dict[str, Any]]:
    """Entries `{name, text, ...}` of `csl_clean.<split>` (gzip pickle list of dicts)."""
    if split not in SPLITS:
        raise InputError(root, "split", f"expected one of {', '.join(SPLITS)}, got {split!r}")
    path = root / f"csl_clean.{split}"
    if not path.is_file():
        raise InputError(path, None, "split file not found")
    entries = read_pickle(path, gz=True)
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "name" in e for e in entries):
        raise InputError(path, "name", "expected a list of dicts with 'name' and 'text'")
    return entries
