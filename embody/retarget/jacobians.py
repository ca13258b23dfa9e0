"""Small geometric kernels shared by the IK's residual terms (`costs.py`, `hand_clearance.py`).

Why: the terms' Jacobians are n·(z × (x − o)) for many (point, joint) pairs;
numpy's generic path for these (`np.cross` on (A,J,3) arrays) was a sizeable share of the solve.
"""

from __future__ import annotations

import numpy as np


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`np.cross` of 3-vectors on the last axis (broadcast), bit for bit: the same products and
    differences (a₁b₂ − a₂b₁, a₂b₀ − a₀b₂, a₀b₁ − a₁b₀), without its axis moves and checks
    (~0.1 ms a call, ~2800 calls in 8 sequences' IK)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def normal_jacobian(z: np.ndarray, o: np.ndarray, frame: np.ndarray, x: np.ndarray,
                    n: np.ndarray) -> np.ndarray:
    """∂(n·x)/∂q (A,J) of points x (A,3) at frames `frame` (A,) along fixed directions n (A,3),
    as if every joint moved them (mask afterwards): n·(z × (x − o)) = z·(x × n) − n·(z × o), so
    the per-joint moment z × o is taken once per frame instead of a lever per point and joint
    (~10× less work than crossing (A,J,3) arrays)."""
    zm = np.concatenate([z, cross(z, o)], -1)[frame]  # (A,J,6)
    return (zm @ np.concatenate([cross(x, n), -n], -1)[:, :, None])[..., 0]
