"""Bounds on what one input may hold (`io` config): frames, frame rate, pose and translation.

A hostile or broken file must fail with one clear error, before it can exhaust memory (4 M
frames of zeros compress to 2.5 MB) or poison every later stage (fps 1e-9, poses of 1e30).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from embody.config.io import IOConfig
from embody.errors import InputError
from embody.io.safe_pickle import Budget

DEFAULT = IOConfig()
#: Widest per-frame layout read (SignAvatars, 182) rounded up: bounds any one array's size.
VALUES_PER_FRAME = 256


#: Input bytes a motion pickle may take per value it may hold: float64 arrays take 8, pickled
#: lists of floats 9, protocol-0 text floats up to ~25 (those reach only part of the bound).
PICKLE_BYTES_PER_VALUE = 16
#: Largest pickle read at all (decompressed, for gzip files).
MAX_PICKLE_BYTES = 1 << 30


def pickle_budget(limits: IOConfig | None = None) -> Budget:
    """What a motion pickle may hold: the values `max_frames` frames can hold, checked on the
    stream before anything is built (so no list or shared reference expands past it)."""
    limits = limits or DEFAULT
    values = limits.max_frames * VALUES_PER_FRAME
    return Budget(max_bytes=min(MAX_PICKLE_BYTES, PICKLE_BYTES_PER_VALUE * values + (1 << 20)),
                  max_elements=values, max_rows=limits.max_frames)


def check_array_header(path: Path | str, key: str, shape: tuple[int, ...],
                       limits: IOConfig | None = None) -> None:
    """Refuse an array from its header alone (before decompressing or allocating it)."""
    limits = limits or DEFAULT
    if len(shape) >= 2 and shape[0] > limits.max_frames:
        raise InputError(path, key, f"{shape[0]} frames exceeds io.max_frames={limits.max_frames}")
    size = math.prod(shape)
    if size > limits.max_frames * VALUES_PER_FRAME:
        raise InputError(path, key, f"{size} values is more than io.max_frames="
                                    f"{limits.max_frames} frames can hold")


def check_frame_count(path: Path | str, frames: int, limits: IOConfig | None = None,
                      key: str = "frames") -> None:
    limits = limits or DEFAULT
    if frames > limits.max_frames:
        raise InputError(path, key, f"{frames} frames exceeds io.max_frames={limits.max_frames}")


def check_fps(path: Path | str, fps: float, limits: IOConfig | None = None) -> None:
    limits = limits or DEFAULT
    if not (math.isfinite(fps) and limits.min_fps <= fps <= limits.max_fps):
        raise InputError(path, "fps", f"{fps:g} is outside io.min_fps..io.max_fps "
                                      f"({limits.min_fps:g}..{limits.max_fps:g})")


def check_motion(motion, limits: IOConfig | None = None) -> None:
    """Frames, fps, |axis-angle| and |translation| of a loaded motion within `limits`."""
    limits = limits or DEFAULT
    where = motion.source.path or "<motion>"
    check_frame_count(where, motion.num_frames, limits)
    check_fps(where, motion.fps, limits)
    angle = np.linalg.norm(motion.pose.astype(np.float64), axis=-1)
    if angle.size and angle.max() > limits.max_axis_angle:
        t, j = np.unravel_index(int(np.argmax(angle)), angle.shape)
        raise InputError(where, "pose", f"|axis-angle| {angle[t, j]:.3g} rad at frame {t}, "
                                        f"joint {j} exceeds io.max_axis_angle="
                                        f"{limits.max_axis_angle:.4g}")
    reach = np.abs(motion.transl).max() if motion.transl.size else 0.0
    if reach > limits.max_translation:
        raise InputError(where, "transl", f"|translation| {reach:.3g} m exceeds "
                                          f"io.max_translation={limits.max_translation:g}")
