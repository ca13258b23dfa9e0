"""The canonical motion type every stage consumes and produces."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from embody.errors import InputError

NUM_JOINTS = 55
NUM_BETAS = 10
HandConvention = Literal["relative", "absolute"]

#: The frame rate at which per-frame smoothness weights are stated (the synthetic data's and
#: SOKE's): the IK's `w_smooth`/`w_jerk`, the collision step's `lambda_smooth`.
WEIGHT_FPS = 30.0


def smoothness_scale(fps: float, order: int) -> float:
    """Factor on a per-frame Δ^k x penalty so that the same motion costs the same against the
    per-frame data terms (tracking, closeness) at any frame rate: Δ^k x shrinks as dt^k, so
    Σ(Δ^k x)² over 1/dt frames falls as dt^(2k-1) while a per-frame data term grows as 1/dt.
    Unscaled, a 120 fps clip gets 1/256 of the 30 fps clip's smoothing (Δ²): the IK's wrists
    chatter and the collision step's correction is rough from frame to frame."""
    return (fps / WEIGHT_FPS) ** (2 * order)

#: SMPL-X kinematic tree (55 joints): body 0-21, jaw 22, eyes 23-24, left hand 25-39, right 40-54.
PARENTS = np.array(
    [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
     20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
     21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53],
    dtype=np.int64,
)
JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "jaw", "left_eye", "right_eye",
    "left_index1", "left_index2", "left_index3", "left_middle1", "left_middle2", "left_middle3",
    "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1", "left_ring2", "left_ring3",
    "left_thumb1", "left_thumb2", "left_thumb3",
    "right_index1", "right_index2", "right_index3", "right_middle1", "right_middle2",
    "right_middle3", "right_pinky1", "right_pinky2", "right_pinky3", "right_ring1", "right_ring2",
    "right_ring3", "right_thumb1", "right_thumb2", "right_thumb3",
)
LEFT_HAND = slice(25, 40)
RIGHT_HAND = slice(40, 55)


@dataclass(frozen=True)
class MotionSource:
    """Where a motion came from, so conversions stay traceable."""

    path: str = ""
    format: str = "unknown"
    hand_convention: HandConvention = "absolute"
    #: Where the source's fps, up axis and hand convention came from (`embody.io.conventions`):
    #: `{"fps"|"up_axis"|"hands": {"value": ..., "origin": "..."}}`.
    provenance: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)


@dataclass
class Motion:
    """SMPL-X motion: axis-angle pose (T,55,3), y-up, hands absolute (flat hand = zero).

    `meta` carries free-form facts such as the sign text or injected synthetic artifacts.
    """

    pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray
    fps: float
    gender: str = "neutral"
    up_axis: str = "y"
    source: MotionSource = field(default_factory=MotionSource)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.pose = np.asarray(self.pose, dtype=np.float32)
        self.transl = np.asarray(self.transl, dtype=np.float32)
        self.betas = np.asarray(self.betas, dtype=np.float32).reshape(-1)
        self.validate()

    @property
    def num_frames(self) -> int:
        return int(self.pose.shape[0])

    @property
    def duration(self) -> float:
        return self.num_frames / self.fps

    def validate(self) -> None:
        """Reject anything downstream stages cannot trust; errors name file and field."""
        where = self.source.path or "<motion>"
        if self.pose.ndim != 3 or self.pose.shape[1:] != (NUM_JOINTS, 3):
            raise InputError(where, "pose", f"expected shape (T, {NUM_JOINTS}, 3), got {self.pose.shape}")
        t = self.pose.shape[0]
        if t < 2:
            raise InputError(where, "pose", f"need at least 2 frames, got {t}")
        if self.transl.shape != (t, 3):
            raise InputError(where, "transl", f"expected shape ({t}, 3), got {self.transl.shape}")
        if self.betas.shape != (NUM_BETAS,):
            raise InputError(where, "betas", f"expected {NUM_BETAS} values, got {self.betas.shape[0]}")
        for name in ("pose", "transl", "betas"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise InputError(where, name, "contains non-finite values (NaN or inf)")
        try:
            fps = float(self.fps)
        except (TypeError, ValueError):
            raise InputError(where, "fps", f"not a number: {self.fps!r}") from None
        if not np.isfinite(fps) or fps <= 0:
            raise InputError(where, "fps", f"must be > 0, got {self.fps!r}")
        self.fps = fps
        if self.up_axis != "y":
            raise InputError(where, "up_axis", f"motions are normalised to y-up, got {self.up_axis!r}")

    def with_pose(self, pose: np.ndarray, transl: np.ndarray | None = None) -> "Motion":
        """A copy with new pose (and optionally translation); everything else kept."""
        return replace(self, pose=np.array(pose, dtype=np.float32),
                       transl=self.transl.copy() if transl is None else np.asarray(transl),
                       meta=dict(self.meta))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays for the artifact store (see docs/ARCHITECTURE.md, "Artifacts")."""
        return {"pose": self.pose, "transl": self.transl, "betas": self.betas}

    def to_attrs(self) -> dict[str, Any]:
        return {"fps": self.fps, "gender": self.gender, "up_axis": self.up_axis,
                "source": {"path": self.source.path, "format": self.source.format,
                           "hand_convention": self.source.hand_convention,
                           "provenance": self.source.provenance},
                "meta": self.meta}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "Motion":
        return cls(pose=np.asarray(arrays["pose"]), transl=np.asarray(arrays["transl"]),
                   betas=np.asarray(arrays["betas"]), fps=attrs["fps"], gender=attrs["gender"],
                   up_axis=attrs.get("up_axis", "y"), source=MotionSource(**attrs["source"]),
                   meta=dict(attrs.get("meta", {})))

    def pose165(self) -> np.ndarray:
        """The flat (T,165) SMPL-X layout used by AMASS-style files."""
        return self.pose.reshape(self.num_frames, NUM_JOINTS * 3)


def resample_motion(motion: Motion, fps: float) -> Motion:
    """`motion` sampled at `fps` over the same duration: each joint's rotation by spherical
    linear interpolation (slerp), the translation linearly. The same motion at another rate."""
    from scipy.spatial.transform import Rotation, Slerp

    t0 = np.arange(motion.num_frames) / motion.fps
    t1 = np.arange(int(np.floor(t0[-1] * fps + 1e-9)) + 1) / fps
    pose = np.stack([Slerp(t0, Rotation.from_rotvec(motion.pose[:, j]))(t1).as_rotvec()
                     for j in range(motion.pose.shape[1])], 1)
    transl = np.stack([np.interp(t1, t0, motion.transl[:, i]) for i in range(3)], 1)
    return replace(motion, pose=pose, transl=transl, fps=float(fps), meta=dict(motion.meta))
