"""A JSON-able description of a motion: what `embody inspect` prints."""

from __future__ import annotations

from typing import Any

import numpy as np

from embody.motion import Motion

#: Joint groups reported by `inspect`, in SMPL-X joint indices.
JOINT_GROUPS: dict[str, tuple[int, ...]] = {
    "root": (0,),
    "legs": (1, 2, 4, 5, 7, 8, 10, 11),
    "spine": (3, 6, 9),
    "neck_head": (12, 15),
    "left_arm": (13, 16, 18, 20),
    "right_arm": (14, 17, 19, 21),
    "jaw_eyes": (22, 23, 24),
    "left_hand": tuple(range(25, 40)),
    "right_hand": tuple(range(40, 55)),
}


def joint_ranges(motion: Motion) -> dict[str, dict[str, float]]:
    """Per group: min and max joint rotation angle (degrees) over its joints and all frames."""
    angles = np.degrees(np.linalg.norm(motion.pose.astype(np.float64), axis=-1))
    return {name: {"min_deg": round(float(angles[:, list(idx)].min()), 2),
                   "max_deg": round(float(angles[:, list(idx)].max()), 2)}
            for name, idx in JOINT_GROUPS.items()}


def summarize(motion: Motion) -> dict[str, Any]:
    out: dict[str, Any] = {
        "path": motion.source.path,
        "format": motion.source.format,
        "frames": motion.num_frames,
        "fps": motion.fps,
        "duration_s": round(motion.duration, 3),
        "hand_convention": motion.source.hand_convention,
        "provenance": motion.source.provenance,
        "gender": motion.gender,
        "translation_range_m": np.round(np.ptp(motion.transl, axis=0), 4).tolist(),
        "joint_ranges": joint_ranges(motion),
    }
    for key in ("text", "gloss", "artifacts", "seed", "generator"):
        if key in motion.meta:
            out[key] = motion.meta[key]
    return out
