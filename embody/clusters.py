"""Point clusters for broad phases: recursive median cuts along the longest axis.

Why one module: the collision energy's chunks (body points skinned and culled together) and
the IK hand clearance's clusters (hand proxy points culled by one ball) are the same split.
"""

from __future__ import annotations

import numpy as np


def median_cuts(points: np.ndarray, size: int) -> list[np.ndarray]:
    """Indices of `points` (N,3) in groups of ≤ `size`: each group over `size` is cut at its
    median along its longest axis (stable sort, so deterministic), left half first."""
    def split(idx: np.ndarray) -> list[np.ndarray]:
        if len(idx) <= size:
            return [idx]
        p = points[idx]
        axis = int(np.argmax(p.max(0) - p.min(0)))
        order = idx[np.argsort(p[:, axis], kind="stable")]
        half = len(order) // 2
        return split(order[:half]) + split(order[half:])
    return split(np.arange(len(points)))
