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
    n, m = cost.shape
    acc = np.full((n + 1, m + 1), np.inf)
    steps = np.zeros((n + 1, m + 1))
    acc[0, 0] = 0.0
    # Cells on one anti-diagonal (i + j = d) depend only on the two before it, so each diagonal
    # is one vectorised step; ties go to (diagonal, up, left) in that order, as a cell loop would.
    for d in range(2, n + m + 1):
        i = np.arange(max(1, d - m), min(n, d - 1) + 1)
        j = d - i
        choices = np.stack((acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1]))
        k = np.argmin(choices, axis=0)
        prev_steps = np.stack((steps[i - 1, j - 1], steps[i - 1, j], steps[i, j - 1]))
        cols = np.arange(len(i))
        acc[i, j] = cost[i - 1, j - 1] + choices[k, cols]
        steps[i, j] = prev_steps[k, cols] + 1
    total = float(acc[n, m])
    return total / steps[n, m] if normalise else total


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
