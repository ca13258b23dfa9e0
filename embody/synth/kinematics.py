"""Aiming wrists at signing-space targets: damped Gauss-Newton IK of both arms on the body
model's forward kinematics, solved for all keyframes of a sequence at once.

The FK is mannequin-x's NumPy skeleton: the same calibrated SMPL-X joints as
`embody.body.MannequinBody`, but free of torch's thread pool, which makes these many tiny
batches ~15x slower on a shared CPU.

Per arm the unknowns are the shoulder rotation (3) and the elbow flexion (1); a weak prior on
the shoulder picks the natural, elbow-down member of the arm's one-parameter family of solutions.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from mannequin import Mannequin

SHOULDER = {"left": 16, "right": 17}
ELBOW = {"left": 18, "right": 19}
#: elbow flexion axis: the forearm bends toward +z (the front).
FLEX_AXIS = {"left": np.array([0.0, -1.0, 0.0]), "right": np.array([0.0, 1.0, 0.0])}
#: upper arm hanging down and a little forward: the posture the prior pulls toward.
SHOULDER_PRIOR = {"left": np.array([0.25, 0.0, -1.15]), "right": np.array([0.25, 0.0, 1.15])}
ELBOW_RANGE = (0.05, 2.6)
MAX_STEP = 0.25


@lru_cache(maxsize=1)
def _skeleton() -> Mannequin:
    return Mannequin("convex", lod=2, flat_hand_mean=True)


class ArmIK:
    """Solves shoulder and elbow angles so both wrists reach their targets."""

    def __init__(self, betas: np.ndarray | None = None) -> None:
        self.skeleton = _skeleton()
        self.betas = np.zeros(10) if betas is None else np.asarray(betas, dtype=np.float64)
        self.wrist = [self.skeleton.joint_index("L_Wrist"), self.skeleton.joint_index("R_Wrist")]

    def _set(self, pose: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Write per-keyframe unknowns q (K,8) into full poses (K,55,3)."""
        out = pose.copy()
        for i, side in enumerate(("left", "right")):
            out[:, SHOULDER[side]] = q[:, 4 * i:4 * i + 3]
            out[:, ELBOW[side]] = q[:, 4 * i + 3, None] * FLEX_AXIS[side]
        return out

    def _wrists(self, pose: np.ndarray) -> np.ndarray:
        transforms = self.skeleton.forward_skeleton(
            pose[:, 1:22], pose[:, 22:25], pose[:, 25:55], global_rotation=pose[:, 0],
            shape=self.betas, joint_indices=self.wrist)
        return transforms[:, :, :3, 3].reshape(-1, 6)

    def wrists(self, pose: np.ndarray) -> np.ndarray:
        """World wrist positions (K,2,3), left then right."""
        return self._wrists(pose).reshape(-1, 2, 3)

    def solve(self, pose: np.ndarray, targets: np.ndarray, iters: int = 20,
              prior: float = 0.04, eps: float = 1e-4,
              shoulders: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Poses (K,55,3) with arms set so wrists reach `targets` (K,2,3); returns (pose, error m).

        Everything but shoulders and elbows (spine, head, wrists, hands) is taken from `pose`.
        `shoulders` (K,2,3), left then right: per-keyframe shoulder priors instead of
        `SHOULDER_PRIOR` (a place the elbow-down posture cannot reach without crossing the body).
        """
        k = pose.shape[0]
        prior_q = np.tile(np.concatenate([SHOULDER_PRIOR["left"], [1.2], SHOULDER_PRIOR["right"], [1.2]]), (k, 1))
        if shoulders is not None:
            prior_q[:, 0:3], prior_q[:, 4:7] = shoulders[:, 0], shoulders[:, 1]
        q = prior_q.copy()
        goal = targets.reshape(k, 6)
        weights = np.array([1, 1, 1, 0, 1, 1, 1, 0], dtype=np.float64) * prior
        eye = np.eye(8)
        for it in range(iters):
            probes = np.concatenate([q[None], q[None] + eps * eye[:, None]], axis=0)  # (9,K,8)
            w = self._wrists(self._set(np.tile(pose, (9, 1, 1)), probes.reshape(-1, 8))).reshape(9, k, 6)
            jac = (w[1:] - w[0]).transpose(1, 2, 0) / eps                            # (K,6,8)
            lam = weights if it < iters - 4 else weights * 0.1
            res = np.concatenate([w[0] - goal, lam * (q - prior_q)], axis=1)          # (K,14)
            full = np.concatenate([jac, np.broadcast_to(np.diag(lam), (k, 8, 8))], axis=1)
            jt = full.transpose(0, 2, 1)
            step = np.linalg.solve(jt @ full + 1e-3 * eye, (jt @ res[..., None]))[..., 0]
            # a trust region keeps every keyframe on the same smooth branch of solutions
            norm = np.linalg.norm(step.reshape(k, 2, 4), axis=-1, keepdims=True)
            q = q - (step.reshape(k, 2, 4) * np.minimum(1.0, MAX_STEP / np.maximum(norm, 1e-12))).reshape(k, 8)
            q[:, 3] = np.clip(q[:, 3], *ELBOW_RANGE)
            q[:, 7] = np.clip(q[:, 7], *ELBOW_RANGE)
        solved = self._set(pose, q)
        err = np.linalg.norm(self.wrists(solved) - targets, axis=-1)
        return solved, err
