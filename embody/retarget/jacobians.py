"""Small geometric kernels shared by the IK's residual terms (`costs.py`, `hand_clearance.py`).

Why: the terms' Jacobians are n·(z × (x − o)) for many (point, joint) pairs;
numpy's generic path for these (`np.cross` on (A,J,3) arrays) was a sizeable share of the solve.
"""

from __future__ import annotations

import numpy as np


def normal_jacobian(z: np.ndarray, o: np.ndarray, frame: np.ndarray, x: np.ndarray,
                    n: np.ndarray) -> np.ndarray:
    """∂(n·x)/∂q (A,J) of points x (A,3) at frames `frame` (A,) along fixed directions n (A,3),
    as if every joint moved them (mask afterwards): n·(z × (x − o)) = z·(x × n) − n·(z × o), so
    the per-joint moment z × o is taken once per frame instead of a lever per point and joint
    (~10× less work than crossing (A,J,3) arrays)."""
    zm = np.concatenate([z, np.cross(z, o)], -1)[frame]  # (A,J,6)
    return (zm @ np.concatenate([np.cross(x, n), -n], -1)[:, :, None])[..., 0]
