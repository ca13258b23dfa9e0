"""Trajectory metrics in NumPy: position/rotation errors, DTW distance and jerk.

They are used both to score the IK (against its own targets, frame by frame) and by the critic
(against the human motion, where timing may drift, hence the DTW variant).
"""

from __future__ import annotations

import numpy as np


def position_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance over the last axis: (..., 3) × (..., 3) → (...)."""
    return np.linalg.norm(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64), axis=-1)


def rotation_error_deg(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Geodesic angle in degrees between rotation matrices (..., 3, 3) → (...)."""
    ra = np.asarray(ra, dtype=np.float64)
    rb = np.asarray(rb, dtype=np.float64)
    trace = np.einsum("...ij,...ij->...", ra, rb)  # trace(ra^T rb)
    cos = np.clip((trace - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def dtw_distance(a: np.ndarray, b: np.ndarray, *, normalise: bool = True) -> float:
    """Dynamic-time-warping distance between two trajectories (Ta, ...) and (Tb, ...).

    Frame cost is the Euclidean distance of the flattened frames. With `normalise` the total
    cost is divided by the warping path length, so it reads in the units of one frame's error.
    O(Ta·Tb) time and memory: fine for sign sequences of a few hundred frames.
    """
    a = np.asarray(a, dtype=np.float64).reshape(len(a), -1)
    b = np.asarray(b, dtype=np.float64).reshape(len(b), -1)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"frame sizes differ: {a.shape[1]} vs {b.shape[1]}")
    cost = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    from embody.metrics.warping import warping_path  # numba: on first use

    total, steps = warping_path(cost)
    return float(total) / np.float64(steps) if normalise else float(total)


def jerk(x: np.ndarray, fps: float) -> np.ndarray:
    """Per-frame jerk magnitude of a trajectory (T, ...) sampled at `fps` → (T-3,).

    Third finite difference scaled by fps³; the norm is taken over all non-time axes, so it
    applies to joint trajectories (T,n) and point trajectories (T,k,3) alike.
    """
    x = np.asarray(x, dtype=np.float64)
    if len(x) < 4:
        return np.zeros(0)
    d3 = np.diff(x, n=3, axis=0) * fps**3
    return np.linalg.norm(d3.reshape(len(d3), -1), axis=-1)


def mean_jerk(x: np.ndarray, fps: float) -> float:
    """Mean jerk magnitude; 0 for sequences shorter than 4 frames."""
    j = jerk(x, fps)
    return float(j.mean()) if len(j) else 0.0
