"""Direct solve of the symmetric banded systems of whole-sequence Gauss-Newton.

Frames couple only through the smoothness and velocity terms, which act joint by joint, so the
blocks off the diagonal are diagonal matrices. With frame-major unknown order the matrix is then
banded with half-bandwidth 2n, and LAPACK's banded Cholesky (`scipy.linalg.solveh_banded`)
solves all frames jointly in O(T·n³) with one call; the band is filled diagonal by diagonal.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded


def block_pentadiagonal_solve(diag: np.ndarray, off1: np.ndarray, off2: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve A x = rhs for SPD A with blocks A[t,t] = diag[t], A[t,t+1] = Diag(off1[t]) and
    A[t,t+2] = Diag(off2[t]).

    Shapes: diag (T,n,n), off1 (T-1,n), off2 (T-2,n), rhs (T,n) → x (T,n).
    """
    return block_banded_solve(diag, [off1, off2], rhs)


def block_banded_solve(diag: np.ndarray, offs: list[np.ndarray], rhs: np.ndarray) -> np.ndarray:
    """`block_pentadiagonal_solve` with any number of diagonal off-blocks: A[t,t+k] = Diag(offs[k-1][t])
    (offs[k-1] (T-k,n)); a third difference (jerk) term needs three."""
    t, n, _ = diag.shape
    ab = np.zeros((min(len(offs) * n + 1, t * n), t * n))  # lower form: ab[d, j] = A[j + d, j]
    for d in range(min(n, len(ab))):  # inside the diagonal blocks: A[sn + c + d, sn + c]
        ab[d].reshape(t, n)[:, : n - d] = np.diagonal(diag, offset=-d, axis1=1, axis2=2)
    for k, off in enumerate(offs, 1):
        if k * n < len(ab) and len(off):
            ab[k * n, : len(off) * n] = off.reshape(-1)
    return solveh_banded(ab, rhs.reshape(-1), lower=True, check_finite=False).reshape(t, n)
