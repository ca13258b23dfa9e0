"""Direct solve of the symmetric block-pentadiagonal systems of whole-sequence Gauss-Newton.

With frame-major unknown order the matrix is banded (half-bandwidth 3n − 1), so LAPACK's banded
Cholesky (`scipy.linalg.solveh_banded`) solves all frames jointly in O(T·n³) with one call; the
band is filled by fancy indexing, no Python loop over frames.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded


def block_pentadiagonal_solve(diag: np.ndarray, off1: np.ndarray, off2: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve A x = rhs for SPD A with blocks A[t,t]=diag[t], A[t,t+1]=off1[t], A[t,t+2]=off2[t].

    Shapes: diag (T,n,n), off1 (T-1,n,n), off2 (T-2,n,n), rhs (T,n) → x (T,n).
    """
    t, n, _ = diag.shape
    width = min(3 * n, t * n)  # rows of the lower band: offsets 0 .. 3n − 1
    ab = np.zeros((width, t * n))
    row, col = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")  # row b, column c in a block
    for k, blocks in enumerate((diag, off1, off2)):
        if len(blocks) == 0:
            continue
        d = k * n + row - col
        keep = (d >= 0) & (d < width)
        s = np.arange(len(blocks))[:, None]
        # A[(s+k)n + b, sn + c] = blocks[s][c, b] (the transpose of the upper block)
        ab[d[keep][None, :].repeat(len(blocks), 0), s * n + col[keep][None, :]] = blocks[:, col[keep], row[keep]]
    return solveh_banded(ab, rhs.reshape(-1), lower=True, check_finite=False).reshape(t, n)
