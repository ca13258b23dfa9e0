"""`load(path)`: detect a motion file's format from its suffix (or first bytes) and read it."""

from __future__ import annotations

import math
from pathlib import Path

from embody.config.io import IOConfig
from embody.errors import InputError
from embody.io import amass, arrays, signavatars, soke
from embody.io.fields import read_npz, read_pickle
from embody.io.limits import check_frame_count, check_motion
from embody.motion import Motion

#: Frame rate of formats that do not record one (CSL-Daily and How2Sign video are ~30 fps).
DEFAULT_FPS = 30.0
#: Suffixes a dataset folder treats as one motion file each.
MOTION_SUFFIXES = (".npz", ".npy", ".pkl", ".pickle")
_MAGIC = {b"PK": ".npz", b"\x93N": ".npy", b"\x80": ".pkl"}


def _kind(path: Path) -> str:
    if path.suffix.lower() in MOTION_SUFFIXES:
        return path.suffix.lower()
    try:
        with path.open("rb") as fh:
            head = fh.read(2)
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    for magic, kind in _MAGIC.items():
        if head.startswith(magic):
            return kind
    raise InputError(path, None, f"unknown motion format (suffix {path.suffix or 'none'!r})")


def _load_dir(path: Path, fps: float, limits: IOConfig | None) -> Motion:
    if soke.is_sequence_dir(path):
        check_frame_count(path, len(soke.frame_files(path)), limits)  # before reading any
        return soke.read(path, fps)
    if not any(path.iterdir()):
        raise InputError(path, None, "empty directory")
    if (path / "poses").is_dir():
        raise InputError(path, None, "a SOKE dataset root: use load_dataset(path, split)")
    raise InputError(path, None, "directory has no per-frame .pkl files (not a SOKE sequence)")


def load(path: str | Path, fps: float | None = None, limits: IOConfig | None = None) -> Motion:
    """Read any supported motion file or SOKE sequence folder as a y-up, absolute-hand Motion.

    `fps` is the frame rate of formats that store none (SOKE, SignAvatars, plain arrays; 30 if
    not given); files that record their rate keep it. `limits` (the `io` config) bounds frames,
    fps, pose and translation; sizes are checked before decompression where the format allows.
    """
    motion = _load(Path(path), fps, limits)
    check_motion(motion, limits)
    return motion


def _load(path: Path, fps: float | None, limits: IOConfig | None) -> Motion:
    if fps is None:
        fps = DEFAULT_FPS
    elif not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError(path, "fps", f"must be a positive number, got {fps!r}")
    if path.is_dir():
        return _load_dir(path, fps, limits)
    if not path.exists():
        raise InputError(path, None, "no such file or directory")
    kind = _kind(path)
    if kind == ".npy":
        return arrays.read(path, fps=fps, limits=limits)
    if kind == ".npz":
        data = read_npz(path, limits)
        return amass.read(path, data) if amass.is_amass(data) else arrays.read(path, data, fps)
    data = read_pickle(path)
    if signavatars.is_signavatars(data):
        return signavatars.read(path, data, fps)
    if isinstance(data, dict) and "smplx_root_pose" in data:
        raise InputError(path, None, "a single SOKE frame: load its sequence folder instead")
    keys = ", ".join(sorted(map(str, data))[:8]) if isinstance(data, dict) else type(data).__name__
    raise InputError(path, None, f"unknown pickle layout ({keys})")
