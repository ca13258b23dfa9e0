"""Body parts by dominant skinning weight, the same rule for every backend.

Each vertex belongs to the joint with its largest skinning weight; joints listed in `merge` hand
their vertices to another joint (by default fingers go to the wrist and the face joints to the
head, the split VolumetricSMPL uses). A part is named after, and driven by, its joint.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

_FINGERS = ("index", "middle", "pinky", "ring", "thumb")


def default_merge(name: str) -> str:
    """Fingers and zero-length hand joints → wrist; jaw and eyes → head; others unchanged."""
    side = name.split("_", 1)[0]
    if side in ("left", "right"):
        rest = name.split("_", 1)[1]
        if rest == "hand" or rest.rstrip("123") in _FINGERS:
            return f"{side}_wrist"
        if rest == "eye":
            return "head"
    if name == "jaw":
        return "head"
    return name


@dataclass(frozen=True)
class Parts:
    """`names[i]` is driven by joint `joints[i]`; `vertex_parts` (V,) indexes `names`."""

    names: tuple[str, ...]
    joints: np.ndarray
    vertex_parts: np.ndarray


def dominant_parts(skin_weights: np.ndarray, joint_names: Sequence[str],
                   merge: Callable[[str], str] = default_merge) -> Parts:
    """Segment vertices by the argmax of their (V,J) skinning weights, then merge joints."""
    owner = np.asarray(skin_weights).argmax(axis=1)
    target = np.array([joint_names.index(merge(name)) for name in joint_names], dtype=np.int64)
    vertex_joint = target[owner]
    joints = np.unique(vertex_joint)
    vertex_parts = np.searchsorted(joints, vertex_joint).astype(np.int64)
    return Parts(tuple(joint_names[j] for j in joints), joints, vertex_parts)
