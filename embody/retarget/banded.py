"""Direct solve of the symmetric banded systems of whole-sequence Gauss-Newton.

Frames couple only through the smoothness and velocity terms, which act joint by joint, so the
blocks off the diagonal are diagonal matrices. With frame-major unknown order the matrix is then
banded with half-bandwidth 2n, and LAPACK's banded Cholesky (`scipy.linalg.solveh_banded`)
solves all frames jointly in O(T·n³) with one call; the band is filled diagonal by diagonal.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.linalg import get_lapack_funcs, solveh_banded


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
    rows = min(len(offs) * n + 1, t * n)
    # lower form ab[d, j] = A[j + d, j], built as its transpose: ab in Fortran order is what
    # LAPACK reads, so `pbsv` factors it in place (no (rows, T·n) copy per LM step)
    abt = np.zeros((t * n, rows))
    dst, src = _block_lower(t, n, rows)  # inside the diagonal blocks: A[sn + c + d, sn + c]
    abt.reshape(-1)[dst] = diag.reshape(-1)[src]
    for k, off in enumerate(offs, 1):
        if k * n < rows and len(off):
            abt[: len(off) * n, k * n] = off.reshape(-1)
    if rows <= 2:  # solveh_banded's tridiagonal path (ptsv) there
        return solveh_banded(abt.T, rhs.reshape(-1), lower=True, check_finite=False).reshape(t, n)
    _, x, info = _pbsv(abt.T, rhs.reshape(-1), lower=1, overwrite_ab=1, overwrite_b=0)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}th leading minor not positive definite")
    if info < 0:
        raise ValueError(f"illegal value in {-info}th argument of internal pbsv")
    return x.reshape(t, n)


#: LAPACK's banded Cholesky solve (what `solveh_banded` calls for a band of ≥ 2 rows)
_pbsv = get_lapack_funcs(("pbsv",), (np.zeros((2, 2)),))[0]


@lru_cache(maxsize=32)
def _block_lower(t: int, n: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices taking the diagonal blocks' lower triangles (T,n,n) into the transposed band
    (T·n, rows): one gather instead of a strided copy per diagonal (the band is rebuilt every LM step)."""
    d, c = np.tril_indices(n)  # row d ≥ column c inside a block: band row d − c, column c
    d, c = d[d - c < rows], c[d - c < rows]
    s = np.arange(t)[:, None]
    dst = (s * n + c[None]) * rows + (d - c)[None]
    src = s * n * n + d[None] * n + c[None]
    return dst.reshape(-1), src.reshape(-1)
