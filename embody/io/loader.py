"""`load(path)`: detect a motion file's format from its suffix (or first bytes) and read it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from embody.config.io import IOConfig
from embody.errors import InputError
from embody.io import amass, arrays, signavatars, soke
from embody.io.conventions import Overrides
from embody.io.fields import read_npz, read_pickle
from embody.io.limits import check_frame_count, check_motion, pickle_budget
from embody.motion import Motion

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


def _load_dir(path: Path, overrides: Overrides, limits: IOConfig | None) -> Motion:
    if soke.is_sequence_dir(path):
        check_frame_count(path, len(soke.frame_files(path)), limits)  # before reading any
        return soke.read(path, overrides)
    if not any(path.iterdir()):
        raise InputError(path, None, "empty directory")
    if (path / "poses").is_dir():
        raise InputError(path, None, "a SOKE dataset root: use load_dataset(path, split)")
    raise InputError(path, None, "directory has no per-frame .pkl or .npz frame files "
                                 "(not a sequence folder)")


def load(path: str | Path, fps: float | None = None, up_axis: str | None = None,
         hands: str | None = None, limits: IOConfig | None = None) -> Motion:
    """Read any supported motion file or per-frame sequence folder as a y-up, absolute-hand Motion.

    Frame rate, up axis and hand convention come from the file where it records them, else from
    the detected layout or the dataset's documented default (`embody.io.conventions`); `fps`,
    `up_axis` ("y" | "z" | "camera") and `hands` ("absolute" | "relative") override all of them.
    `motion.source.provenance` says where each came from. `limits` (the `io` config) bounds
    frames, fps, pose and translation; sizes are checked before decompression where the format
    allows.
    """
    path = Path(path)
    overrides = Overrides(fps=fps, up_axis=up_axis, hands=hands)
    overrides.check(path)
    motion = _load(path, overrides, limits)
    check_motion(motion, limits)
    return motion


def _load(path: Path, overrides: Overrides, limits: IOConfig | None) -> Motion:
    if path.is_dir():
        return _load_dir(path, overrides, limits)
    if not path.exists():
        raise InputError(path, None, "no such file or directory")
    kind = _kind(path)
    if kind == ".npy":
        return arrays.read(path, overrides=overrides, limits=limits)
    if kind == ".npz":
        data = read_npz(path, limits)
        if amass.is_amass(data):
            return amass.read(path, data, overrides)
        if "smplx_root_pose" in data:
            raise InputError(path, None, "a single per-frame file: load its sequence folder instead")
        return arrays.read(path, data, overrides)
    data = read_pickle(path, budget=pickle_budget(limits))
    if signavatars.is_signavatars(data):
        smplx = data["smplx"]
        if isinstance(smplx, (list, tuple)) or (isinstance(smplx, np.ndarray) and smplx.ndim):
            check_frame_count(path, len(smplx), limits, "smplx")  # before the float64 copy
        return signavatars.read(path, data, overrides)
    if isinstance(data, dict) and "smplx_root_pose" in data:
        raise InputError(path, None, "a single SOKE frame: load its sequence folder instead")
    keys = ", ".join(sorted(map(str, data))[:8]) if isinstance(data, dict) else type(data).__name__
    raise InputError(path, None, f"unknown pickle layout ({keys})")
