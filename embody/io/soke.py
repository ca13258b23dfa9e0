"""Per-frame sequence folders (SOKE, the How2Sign SMPL-X release, fitting pipelines), split files.

One file per frame, `.pkl` or `.npz`, with SOKE's keys (`smplx_root_pose`, `smplx_body_pose`,
`smplx_lhand_pose`, `smplx_rhand_pose`, `smplx_jaw_pose`, optional `smplx_shape`, `cam_trans`).
Frames are ordered by their numeric index (`{video}_{frame}_3D.pkl`, `images0001.pkl`, `7.npz`):
names are not always zero-padded, so lexical order would put frame 10 before frame 9.
Fits are in the camera frame (y down) with mean-relative hands.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError
from embody.io.conventions import Overrides, Setting, normalise
from embody.io.fields import field, read_npz, read_pickle
from embody.io.limits import pickle_budget
from embody.motion import NUM_JOINTS, Motion, MotionSource

SPLITS = ("train", "val", "test")
FRAME_SUFFIXES = (".pkl", ".npz")
#: (key, width, first pose index) in SMPL-X 165 layout; eyes stay zero.
FRAME_FIELDS = (("smplx_root_pose", 3, 0), ("smplx_body_pose", 63, 3), ("smplx_jaw_pose", 3, 66),
                ("smplx_lhand_pose", 45, 75), ("smplx_rhand_pose", 45, 120))

#: How2Sign SMPL-X release: `{video}_{frame}_3D.pkl`.
HOW2SIGN_FRAME = re.compile(r"_(\d+)_3D$")
#: Phoenix-2014T frames as SOKE stores them: `images0001.pkl`.
PHOENIX_FRAME = re.compile(r"^images(\d+)")
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")

# Per-dataset frame rates (none of these files records one). Checked against the datasets' code:
# - How2Sign: SOKE's loader (2000ZRL/SOKE, mGPT/data/humanml/load_data.py, `load_h2s_sample`)
#   reads `{name}_{frame}_3D.pkl` and subsamples every clip faster than 24 fps to 24 fps
#   (`if fps > 24: frame_list = sample(frame_list, count=int(24*len(frame_list)/fps))`), so SOKE's
#   How2Sign data is 24 fps. Raw release frames of a faster clip need `--fps`.
# - Phoenix-2014T: "All recorded videos are at 25 frames per second" (RWTH i6's RWTH-PHOENIX-Weather
#   database page, www-i6.informatik.rwth-aachen.de .../rwth-phoenix/); SOKE's
#   `load_phoenix_sample` keeps every frame, no resampling.
# - CSL-Daily: its videos are 30 fps (a CSL-Daily data description, Lceoliu/slr_new
#   CSL-Daily_README.md: "帧率为 30fps"; the official CSL-Daily page was not reachable to check);
#   SOKE's `load_csl_sample` keeps every frame, no resampling.
HOW2SIGN_FPS = Setting(24.0, "default: How2Sign frame naming; SOKE resamples How2Sign to 24 fps")
PHOENIX_FPS = Setting(25.0, "default: Phoenix-2014T frame naming; its video is 25 fps")
CSL_DAILY_FPS = Setting(30.0, "default: per-frame folder without a known naming; "
                              "CSL-Daily (SOKE's main set) video is 30 fps")
#: A split file lists names and texts, not frames: the default bounds apply whatever
#: `io.max_frames` a run sets (a short `max_frames` must not refuse a long split list).
SPLIT_BUDGET = pickle_budget()
CAMERA_UP = Setting("camera", "default: video fits are in the camera frame (y down)")
RELATIVE_HANDS = Setting("relative", "default: SOKE-style fits store mean-relative hands")


def frame_index(path: Path) -> tuple[int, int, str]:
    """Sort key: the frame number (`_{n}_3D`, `images{n}`, else the last number), then the name."""
    stem = path.stem
    for pattern in (HOW2SIGN_FRAME, PHOENIX_FRAME, _LAST_NUMBER):
        match = pattern.search(stem)
        if match:
            return (0, int(match.group(1)), path.name)
    return (1, 0, path.name)


def _npz_is_frame(path: Path) -> bool:
    """Whether an npz holds one SOKE-style frame (reads the member list only)."""
    try:
        with zipfile.ZipFile(path) as zf:
            return "smplx_root_pose.npy" in zf.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def frame_files(directory: Path) -> list[Path]:
    """The folder's frame files in frame order: all `.pkl`, or `.npz` that hold SOKE keys."""
    try:
        files = [p for p in directory.iterdir() if p.suffix.lower() in FRAME_SUFFIXES and p.is_file()]
    except OSError:
        return []
    pkl = [p for p in files if p.suffix.lower() == ".pkl"]
    npz = [p for p in files if p.suffix.lower() == ".npz"]
    if pkl:
        return sorted(pkl, key=frame_index)
    npz = sorted(npz, key=frame_index)
    return npz if npz and _npz_is_frame(npz[0]) else []


def is_sequence_dir(directory: Path) -> bool:
    return directory.is_dir() and bool(frame_files(directory))


def default_fps(files: list[Path]) -> Setting:
    """The documented frame rate of the dataset the frame naming belongs to."""
    stem = files[0].stem
    if HOW2SIGN_FRAME.search(stem):
        return HOW2SIGN_FPS
    if PHOENIX_FRAME.search(stem):
        return PHOENIX_FPS
    return CSL_DAILY_FPS


def _frame(path: Path) -> dict[str, Any]:
    data = read_npz(path) if path.suffix.lower() == ".npz" else read_pickle(path)
    if not isinstance(data, dict):
        raise InputError(path, None, f"expected a dict of SMPL-X fields, got {type(data).__name__}")
    return data


def _vector(data: dict[str, Any], key: str, width: int, path: Path) -> np.ndarray:
    arr = field(data, key, path).reshape(-1)
    if arr.shape[0] != width:
        raise InputError(path, key, f"expected {width} values, got {arr.shape[0]}")
    return arr


def read(directory: Path, overrides: Overrides | None = None) -> Motion:
    files = frame_files(directory)
    if not files:
        raise InputError(directory, None, "no per-frame .pkl or .npz files (empty sequence folder)")
    suffixes = {p.suffix.lower() for p in directory.iterdir() if p.suffix.lower() in FRAME_SUFFIXES}
    if len(suffixes) > 1:
        raise InputError(directory, None, "mixes per-frame .pkl and .npz files; keep one kind")
    poses = np.zeros((len(files), 165))
    transl = np.zeros((len(files), 3))
    shapes = np.zeros((len(files), 10))
    for i, path in enumerate(files):
        data = _frame(path)
        for key, width, start in FRAME_FIELDS:
            poses[i, start:start + width] = _vector(data, key, width, path)
        shapes[i] = _vector(data, "smplx_shape", 10, path) if "smplx_shape" in data else 0.0
        transl[i] = _vector(data, "cam_trans", 3, path) if "cam_trans" in data else 0.0
    pose, transl, fps, hands, provenance = normalise(
        poses.reshape(-1, NUM_JOINTS, 3), transl, fps=default_fps(files), up_axis=CAMERA_UP,
        hands=RELATIVE_HANDS, overrides=overrides)
    fmt = "frames-npz" if files[0].suffix.lower() == ".npz" else "soke"
    return Motion(pose=pose, transl=transl, betas=shapes.mean(axis=0), fps=fps,
                  source=MotionSource(str(directory), fmt, hands, provenance))  # type: ignore[arg-type]


def read_split(root: Path, split: str) -> list[dict[str, Any]]:
    """Entries `{name, text, ...}` of `csl_clean.<split>` (gzip pickle list of dicts)."""
    if split not in SPLITS:
        raise InputError(root, "split", f"expected one of {', '.join(SPLITS)}, got {split!r}")
    path = root / f"csl_clean.{split}"
    if not path.is_file():
        raise InputError(path, None, "split file not found")
    entries = read_pickle(path, gz=True, budget=SPLIT_BUDGET)
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "name" in e for e in entries):
        raise InputError(path, "name", "expected a list of dicts with 'name' and 'text'")
    return entries
