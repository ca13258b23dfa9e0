"""The mesh judge's skin: `kinematics.skin`'s vertices, bit for bit, as NumPy, compiled.

Why: after the judge's per-frame work was compiled (`collision.frame_kernels`), skinning was
most of its time, and most of that the dense blend `torch.matmul(weights (V,J), bones)`, with
J = 54 joints where a vertex has at most 4 nonzero weights. MKL's dgemm computes each entry as
a chain of fused multiply-adds from +0 in joint order; the zero-weight terms add ±0 and leave
the chain's value and its zero's sign as they are, so the chain over the nonzero weights alone
has the same bits. Another BLAS (or CPU) could sum otherwise: `_sparse_is_exact` checks it once
per process against `torch.matmul`, and the product is used when it differs."""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, types
from numba.extending import intrinsic

from embody.body.kinematics import SKIN_CHUNK


def skin_array(transforms: torch.Tensor, rest_vertices: torch.Tensor,
               bind_positions: torch.Tensor, weights: torch.Tensor,
               sparse: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """`kinematics.skin`'s result, bit for bit, as a NumPy array (T,V,3) without autograd.
    The same bones; the blend either each entry's fused multiply-add chain over the vertex's
    nonzero weights (given `sparse` from `sparse_weights`, on the CPU, where
    `_sparse_is_exact` found it exact) or the same `torch.matmul` per chunk; then the columns
    summed in `skin`'s order ((m0·x + m1·y) + m2·z) + m3 (no fused multiply-add) in one
    compiled pass."""
    global _SPARSE_EXACT
    with torch.no_grad():
        rot = transforms[..., :3, :3]
        trans = transforms[..., :3, 3] - (rot @ bind_positions[..., None])[..., 0]
        bone = torch.cat((rot, trans[..., None]), dim=-1).flatten(-2)  # (T,J,12)
        rest = np.ascontiguousarray(rest_vertices.cpu().numpy(), dtype=np.float64)
        out = np.empty((bone.shape[0], rest.shape[0], 3))
        if (sparse is not None and weights.dtype == torch.float64
                and weights.device.type == "cpu"):
            if _SPARSE_EXACT is None:
                _SPARSE_EXACT = _sparse_is_exact(bone[:8], weights, sparse)
            if _SPARSE_EXACT:
                b = np.ascontiguousarray(bone.cpu().numpy(), dtype=np.float64)
                _skin_sparse(b, *sparse, rest, out)
                return out
        for start in range(0, bone.shape[0], SKIN_CHUNK):
            m = torch.matmul(weights, bone[start:start + SKIN_CHUNK]).cpu().numpy()
            _skin_columns(np.ascontiguousarray(m, dtype=np.float64), rest,
                          out[start:start + SKIN_CHUNK])
    return out


#: Whether `_skin_sparse` gives this machine's `torch.matmul` bits (None: not yet checked).
_SPARSE_EXACT: bool | None = None


def sparse_weights(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joint ids (U,K), weights (U,K), row (V,)): the distinct rows of nonzero weights in
    joint order (K the most per vertex; unused slots weight 0 at joint 0), float64, and each
    vertex's row. Why distinct: a vertex's blended bone is a function of its row alone, and
    on mannequin-x 24,256 vertices share 4,886 rows, so a frame blends each row once."""
    w = np.asarray(weights, dtype=np.float64)
    k = max(int((w != 0).sum(1).max()), 1)
    idx = np.zeros((len(w), k), dtype=np.int64)
    val = np.zeros((len(w), k))
    rows, cols = np.nonzero(w)                    # row-major: by vertex, then joint
    slot = np.arange(len(rows)) - np.searchsorted(rows, rows)
    idx[rows, slot], val[rows, slot] = cols, w[rows, cols]
    key = np.concatenate([idx.astype(np.float64).view(np.uint64),
                          val.view(np.uint64)], 1)  # bits, so -0.0 and 0.0 stay apart
    _, first, row = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return (np.ascontiguousarray(idx[first]), np.ascontiguousarray(val[first]),
            np.ascontiguousarray(row.reshape(-1), dtype=np.int64))


def _sparse_is_exact(bone: torch.Tensor, weights: torch.Tensor,
                     sparse: tuple[np.ndarray, np.ndarray, np.ndarray]) -> bool:
    """Whether the fused multiply-add chains give `torch.matmul`'s bits on this machine (its
    BLAS could sum in another order, or start from another zero): checked once per process
    on these bones and on random ones (some with exact and negative zeros), every vertex and
    entry, signs of zeros included (the first 8 frames' bones and 3 random sets: ~0.1 s)."""
    rng = np.random.default_rng(0)
    noise = rng.normal(size=(3, *bone.shape[1:]))
    noise[1:][rng.random(noise[1:].shape) < 0.5] = 0.0     # exact zeros (identity rotations)
    noise[2] = np.copysign(noise[2], -1.0)                  # and negative ones: -0.0
    probe = torch.cat((bone, torch.as_tensor(noise)))
    ref = torch.matmul(weights, probe.to(weights.dtype)).cpu().numpy()
    ours = np.empty_like(ref)
    _blend(np.ascontiguousarray(probe.cpu().numpy(), dtype=np.float64), *sparse, ours)
    return ours.tobytes() == np.ascontiguousarray(ref).tobytes()


@intrinsic
def _fma(typingctx, a, b, c):
    """a·b + c rounded once (LLVM's llvm.fma)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return sig, codegen


@njit(cache=True, nogil=True)
def _blend(bone: np.ndarray, idx: np.ndarray, val: np.ndarray, row: np.ndarray,
           out: np.ndarray) -> None:
    """out[t,v,c] = Σ_k val[r,k]·bone[t,idx[r,k],c], r = row[v] (T,V,12): per entry a chain
    of fused multiply-adds from +0 in joint order (`_skin_sparse`'s blend)."""
    for t in range(bone.shape[0]):
        for v in range(row.shape[0]):
            r = row[v]
            out[t, v, :] = 0.0
            for k in range(idx.shape[1]):
                w = val[r, k]
                j = idx[r, k]
                for c in range(12):
                    out[t, v, c] = _fma(w, bone[t, j, c], out[t, v, c])


@njit(cache=True, nogil=True)
def _skin_sparse(bone: np.ndarray, idx: np.ndarray, val: np.ndarray, row: np.ndarray,
                 rest: np.ndarray, out: np.ndarray) -> None:
    """`_blend` (each distinct row once a frame) and `_skin_columns` (the chain written
    out: a call per entry costs more than the entry)."""
    m = np.empty((idx.shape[0], 12))
    n_k = idx.shape[1]
    for t in range(bone.shape[0]):
        bt = bone[t]
        for u in range(idx.shape[0]):
            for c in range(12):
                m[u, c] = 0.0
            for k in range(n_k):
                w = val[u, k]
                j = idx[u, k]
                for c in range(12):
                    m[u, c] = _fma(w, bt[j, c], m[u, c])
        for v in range(row.shape[0]):
            mv = m[row[v]]
            x, y, z = rest[v, 0], rest[v, 1], rest[v, 2]
            for r in range(3):
                out[t, v, r] = (((mv[4 * r] * x + mv[4 * r + 1] * y) + mv[4 * r + 2] * z)
                                + mv[4 * r + 3])


@njit(cache=True, nogil=True)
def _skin_columns(m: np.ndarray, rest: np.ndarray, out: np.ndarray) -> None:
    """out[t,v,r] = ((m[t,v,4r]·x + m[t,v,4r+1]·y) + m[t,v,4r+2]·z) + m[t,v,4r+3]."""
    for t in range(m.shape[0]):
        for v in range(m.shape[1]):
            x, y, z = rest[v, 0], rest[v, 1], rest[v, 2]
            for r in range(3):
                out[t, v, r] = ((m[t, v, 4 * r] * x + m[t, v, 4 * r + 1] * y)
                                + m[t, v, 4 * r + 2] * z) + m[t, v, 4 * r + 3]
