"""Plain pose arrays: `.npy` or `.npz` holding (T,165) or (T,55,3) SMPL-X axis-angle, or SOKE's
133-d model features (what its decoder emits).

Assumed absolute hands, y-up, 30 fps (or `load(path, fps=...)`), unless the npz says otherwise
with the optional keys `fps`, `trans`/`transl`, `betas`, `hand_convention` ("relative" |
"absolute") and `up_axis` ("y" | "z").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError
from embody.io.conventions import Overrides, Setting, normalise
from embody.io.fields import betas10, field, read_npy, read_npz, scalar, text
from embody.motion import NUM_JOINTS, Motion, MotionSource


#: SOKE features: upper body (joints 12-21) 0:30 | left hand 30:75 | right hand 75:120 |
#: jaw 120:123 | expression 123:133. Root and joints 1-11 are zero (the decoder prepends 36
#: zeros), shape is fixed, hands are mean-relative. Pairs: (feature slice, first 165-d index).
SOKE_FEATURES = 133
SOKE_PARTS = ((slice(0, 30), 36), (slice(30, 120), 75), (slice(120, 123), 66))
#: Plain arrays record no rate: 30 fps unless the npz says (`fps`) or the user does (`--fps`).
DEFAULT_FPS = Setting(30.0, "default: no frame rate in the file; assumed 30 fps")


def soke_features_to_poses(feats: np.ndarray) -> np.ndarray:
    """(T,133) SOKE features → (T,165) SMPL-X poses (hands still relative; expression dropped)."""
    poses = np.zeros((feats.shape[0], 165), dtype=feats.dtype)
    for src, start in SOKE_PARTS:
        poses[:, start:start + src.stop - src.start] = feats[:, src]
    return poses


def _poses(data: dict[str, Any], key: str, path: Path) -> tuple[np.ndarray, str]:
    """(T,165) poses and the format name."""
    raw = np.asarray(data[key])
    if raw.ndim == 3 and raw.shape[1:] == (NUM_JOINTS, 3):
        return field({key: raw.reshape(raw.shape[0], -1)}, key, path, width=165), "array"
    if raw.ndim == 2 and raw.shape[1] == SOKE_FEATURES:
        feats = field(data, key, path, width=SOKE_FEATURES)
        return soke_features_to_poses(feats), "soke-features"
    return field(data, key, path, width=165), "array"


def read(path: Path, data: dict[str, Any] | None = None,
         overrides: Overrides | None = None, limits: Any = None) -> Motion:
    if data is None:
        data = {"poses": read_npy(path, limits)} if path.suffix == ".npy" else read_npz(path, limits)
    arrays = [k for k in data if np.asarray(data[k]).ndim >= 2]
    if "poses" in data:
        key = "poses"
    elif len(arrays) == 1:
        key = arrays[0]
    else:
        raise InputError(path, "poses", f"missing (arrays present: {', '.join(sorted(data)) or 'none'})")
    poses, fmt = _poses(data, key, path)
    t = poses.shape[0]
    tkey = "trans" if "trans" in data else "transl"
    transl = field(data, tkey, path, rows=t, width=3) if tkey in data else np.zeros((t, 3))
    if "hand_convention" in data:
        hands = Setting(text(data, "hand_convention", "", path), "data: hand_convention")
    elif fmt == "soke-features":
        hands = Setting("relative", "default: SOKE features are mean-relative")
    else:
        hands = Setting("absolute", "default: plain arrays assumed absolute")
    up = (Setting(text(data, "up_axis", "", path), "data: up_axis") if "up_axis" in data
          else Setting("y", "default: plain arrays assumed y-up"))
    if hands.value not in ("absolute", "relative"):
        raise InputError(path, "hand_convention", f"expected 'absolute' or 'relative', got {hands.value!r}")
    if up.value not in ("y", "z"):
        raise InputError(path, "up_axis", f"expected 'y' or 'z', got {up.value!r}")
    fps_key = next((k for k in ("fps", "mocap_frame_rate") if k in data), None)
    fps = (Setting(scalar(data, (fps_key,), path, 0.0), f"data: {fps_key}") if fps_key
           else DEFAULT_FPS)
    pose, transl, fps_value, hand_convention, provenance = normalise(
        poses.reshape(t, NUM_JOINTS, 3), transl, fps=fps, up_axis=up, hands=hands,
        overrides=overrides)
    return Motion(pose=pose, transl=transl, betas=betas10(data, "betas", path), fps=fps_value,
                  gender=text(data, "gender", "neutral", path),
                  source=MotionSource(str(path), fmt, hand_convention, provenance))  # type: ignore[arg-type]
