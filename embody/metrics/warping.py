"""The dynamic-time-warping recursion of `trajectory.dtw_distance`, compiled (numba).

Why: the recursion is one addition and a three-way choice per cell; as NumPy steps over the
anti-diagonals it took ~35 ms per pair of palm paths, twice per fidelity comparison (sequences
of a few hundred frames at the control rate). The loop here makes the same choices and the same
single addition per cell, so the same sums bit for bit. Imported on first use: importing numba
costs a few tenths of a second that the report, which only reads tables, should not pay.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def warping_path(cost: np.ndarray) -> tuple[float, float]:
    """Least accumulated cost of a warping path through `cost` (n,m) from (0,0) to (n-1,m-1),
    and its length (cells). Each cell takes the least of (diagonal, up, left), ties in that
    order and NaN first, as `np.argmin` does."""
    n, m = cost.shape
    acc = np.full((n + 1, m + 1), np.inf)
    steps = np.zeros((n + 1, m + 1))
    acc[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            best, k = acc[i - 1, j - 1], 0
            if not np.isnan(best):
                up = acc[i - 1, j]
                if up < best or np.isnan(up):
                    best, k = up, 1
            if not np.isnan(best):
                left = acc[i, j - 1]
                if left < best or np.isnan(left):
                    best, k = left, 2
            acc[i, j] = cost[i - 1, j - 1] + best
            if k == 0:
                steps[i, j] = steps[i - 1, j - 1] + 1.0
            elif k == 1:
                steps[i, j] = steps[i - 1, j] + 1.0
            else:
                steps[i, j] = steps[i, j - 1] + 1.0
    return acc[n, m], steps[n, m]
