"""Compiled (numba) narrow phase of the collision energy on the CPU: the selection
(`select`, `energy.penetrations` for float32) and the point depths with their gradient
(`PointDepths`, `energy.point_depths`).

Why: after the broad phase was compiled, the optimiser's per-step selection (skin every
candidate point, take it to its part's frame, box filter, the deepest piece's active plane) was
the largest part of a step left (~35 %), as ~40 small tensor ops, and the depths' autograd
graph (per-point gathers, a batched skinning product) most of its backward.

`select` follows the torch selection's float32 arithmetic operation for operation (the
skinning and plane products as fused multiply-add chains, emulated in float64), so the two
select the same points and planes, with plane values equal to float32 rounding; only a point
within rounding of the threshold may be selected by one and not the other (checked in
`tests/test_collision_compiled.py`). `PointDepths` works in float64: equal to the autograd
graph's depths and gradients to rounding (same test file, with gradcheck).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

_ZERO = np.float32(0.0)


@njit(cache=True, nogil=True, inline="always")
def _fma(a: np.float32, b: np.float32, c: np.float32) -> np.float32:
    return np.float32(np.float64(a) * np.float64(b) + np.float64(c))


@njit(cache=True, nogil=True)
def select(blend: np.ndarray, rot: np.ndarray, trans: np.ndarray, chunk_joints: np.ndarray,
           chunk_weights: np.ndarray, chunk_points: np.ndarray, piece_box: np.ndarray,
           planes: np.ndarray, n_planes: np.ndarray, t: np.ndarray, h: np.ndarray,
           n: np.ndarray, b: np.ndarray, k: np.ndarray, first: np.ndarray,
           part_first: np.ndarray, part_inverse: np.ndarray, part_point: np.ndarray,
           reach: np.float32, tolerance: np.float32, n_parts: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, plane index, f) of the penetrating candidate rows: per (frame, chunk, point,
    part b) the row of the deepest piece (least f, ties to the lowest row), in sorted key
    order, f = max over the piece's planes (< −`tolerance`), of the rows within `reach` of
    the piece's box. Arguments as `energy.PointRows` and `energy.CollisionModel` (float32
    model arrays), `blend` (T,J,12), `rot` (T,C,3,3), `trans` (T,C,3)."""
    n_u = chunk_joints.shape[1]
    n_h, n_s = chunk_points.shape[0], chunk_points.shape[1]
    # each distinct point skinned once: Σ_u w_u A_u (an FMA chain over u), then the affine
    world = np.empty((len(first), 3), dtype=np.float32)
    m = np.empty(12, dtype=np.float32)
    for i in range(len(first)):
        r = first[i]
        tt, hh, nn = t[r], h[r], n[r]
        w = chunk_weights[hh, nn]
        # zero weights skipped: fma(0, a, m) is m (up to the sign of a zero result)
        started = False
        for u in range(n_u):
            if w[u] == 0:
                continue
            a = blend[tt, chunk_joints[hh, u]]
            if started:
                for j in range(12):
                    m[j] = _fma(w[u], a[j], m[j])
            else:
                started = True
                for j in range(12):
                    m[j] = w[u] * a[j]
        p = chunk_points[hh, nn]
        for j in range(3):
            world[i, j] = ((m[4 * j] * p[0] + m[4 * j + 1] * p[1]) + m[4 * j + 2] * p[2]) \
                + m[4 * j + 3]
    # each distinct (point, part b) in b's joint frame: Rᵀ(p − t_b)
    local = np.empty((len(part_first), 3), dtype=np.float32)
    for i in range(len(part_first)):
        r = part_first[i]
        rr, tb = rot[t[r], b[r]], trans[t[r], b[r]]
        p = world[part_point[i]]
        x0, x1, x2 = p[0] - tb[0], p[1] - tb[1], p[2] - tb[2]
        for j in range(3):
            local[i, j] = (x0 * rr[0, j] + x1 * rr[1, j]) + x2 * rr[2, j]
    # the box filter, then per piece the count of rows (MKL's product depends on it)
    n_rows = len(t)
    near = np.empty(n_rows, dtype=np.int64)
    count = np.zeros(piece_box.shape[0], dtype=np.int64)
    nn_ = 0
    for r in range(n_rows):
        q = local[part_inverse[r]]
        bx = piece_box[k[r]]
        g0 = max(bx[0, 0] - q[0], _ZERO) + max(q[0] - bx[1, 0], _ZERO)
        g1 = max(bx[0, 1] - q[1], _ZERO) + max(q[1] - bx[1, 1], _ZERO)
        g2 = max(bx[0, 2] - q[2], _ZERO) + max(q[2] - bx[1, 2], _ZERO)
        if np.sqrt(_fma(g2, g2, _fma(g1, g1, g0 * g0))) <= reach:
            near[nn_] = r
            nn_ += 1
            count[k[r]] += 1
    inside = np.empty(nn_, dtype=np.int64)
    arg = np.empty(nn_, dtype=np.int64)
    fv = np.empty(nn_, dtype=np.float32)
    key = np.empty(nn_, dtype=np.int64)
    n_in = 0
    limit = -tolerance
    for i in range(nn_):
        r = near[i]
        q = local[part_inverse[r]]
        pl = planes[k[r]]
        best = np.float32(-np.inf)
        best_j = 0
        # a plane at or above −tolerance settles it: the row is not inside (the max only grows)
        if count[k[r]] < 4:
            for j in range(n_planes[k[r]]):
                v = ((q[0] * pl[j, 0] + q[1] * pl[j, 1]) + q[2] * pl[j, 2]) + pl[j, 3]
                if v > best or j == 0:
                    best, best_j = v, j
                    if not best < limit:
                        break
        else:
            q0, q1, q2 = np.float64(q[0]), np.float64(q[1]), np.float64(q[2])
            for j in range(n_planes[k[r]]):
                v = np.float32(q0 * np.float64(pl[j, 0]))
                v = np.float32(q1 * np.float64(pl[j, 1]) + np.float64(v))
                v = np.float32(q2 * np.float64(pl[j, 2]) + np.float64(v))
                v = v + pl[j, 3]
                if v > best or j == 0:
                    best, best_j = v, j
                    if not best < limit:
                        break
        if best < limit:
            inside[n_in], arg[n_in], fv[n_in] = r, best_j, best
            key[n_in] = ((t[r] * n_h + h[r]) * n_s + n[r]) * n_parts + b[r]
            n_in += 1
    # the deepest piece per (frame, chunk, point, part), in key order
    order = np.argsort(key[:n_in], kind="mergesort")
    keep = np.empty(n_in, dtype=np.int64)
    n_keep = 0
    i = 0
    while i < n_in:
        j = i
        pick = order[i]
        while j < n_in and key[order[j]] == key[order[i]]:
            if fv[order[j]] < fv[pick]:
                pick = order[j]
            j += 1
        keep[n_keep] = pick
        n_keep += 1
        i = j
    keep = keep[:n_keep]
    return inside[keep], arg[keep], fv[keep]


@njit(cache=True, nogil=True)
def select_inputs(transforms: np.ndarray, rest_shift: np.ndarray, part_joints: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`select`'s float32 inputs from float32 transforms (T,J,4,4) of a body whose inverse rest
    transforms are translations (`rest_shift` (J,3)): the skinning transforms (T,J,12) as
    `energy._blend` computes them (t = ((r₀s₀ + r₁s₁) + r₂s₂) + t, float32 operations in that
    order: the same bits), and the parts' joint rotations (T,C,3,3) and origins (T,C,3).

    Why: as tensor ops (a cat, gathers, three contiguous copies) this glue cost about as much
    as a fifth of `select` itself, every step."""
    n_t, n_j = transforms.shape[0], transforms.shape[1]
    blend = np.empty((n_t, n_j, 12), dtype=np.float32)
    rot = np.empty((n_t, len(part_joints), 3, 3), dtype=np.float32)
    trans = np.empty((n_t, len(part_joints), 3), dtype=np.float32)
    for t in range(n_t):
        for j in range(n_j):
            m = transforms[t, j]
            for i in range(3):
                blend[t, j, 4 * i] = m[i, 0]
                blend[t, j, 4 * i + 1] = m[i, 1]
                blend[t, j, 4 * i + 2] = m[i, 2]
                blend[t, j, 4 * i + 3] = ((m[i, 0] * rest_shift[j, 0] + m[i, 1] * rest_shift[j, 1])
                                          + m[i, 2] * rest_shift[j, 2]) + m[i, 3]
        for c in range(len(part_joints)):
            m = transforms[t, part_joints[c]]
            for i in range(3):
                for k in range(3):
                    rot[t, c, i, k] = m[i, k]
                trans[t, c, i] = m[i, 3]
    return blend, rot, trans


@njit(cache=True, nogil=True)
def _blend(transforms: np.ndarray, rest_inverse: np.ndarray) -> np.ndarray:
    """Skinning transforms (T,J,3,4): each joint's world transform times its inverse rest."""
    out = np.zeros((transforms.shape[0], transforms.shape[1], 3, 4))
    blend_at(transforms, rest_inverse, np.arange(transforms.shape[1]), out)
    return out


@njit(cache=True, nogil=True)
def blend_at(transforms: np.ndarray, rest_inverse: np.ndarray, joints: np.ndarray,
             out: np.ndarray) -> None:
    """`_blend` of the given joints only, into `out` (T,J,3,4) (the other joints untouched):
    the optimiser keeps the skinning transforms of the joints its pose never moves."""
    for t in range(transforms.shape[0]):
        for j in joints:
            for a in range(3):
                for c in range(4):
                    out[t, j, a, c] = (transforms[t, j, a, 0] * rest_inverse[j, 0, c]
                                       + transforms[t, j, a, 1] * rest_inverse[j, 1, c]
                                       + transforms[t, j, a, 2] * rest_inverse[j, 2, c]
                                       + transforms[t, j, a, 3] * rest_inverse[j, 3, c])


@njit(cache=True, nogil=True)
def _depth_terms(blend: np.ndarray, transforms: np.ndarray, part_joints: np.ndarray,
                 chunk_joints: np.ndarray, chunk_weights: np.ndarray, chunk_points: np.ndarray,
                 t: int, h: int, n: int, b: int, x: np.ndarray) -> None:
    """x = p − t_b for the skinned point (frame t, chunk h, point n) and part b."""
    jb = part_joints[b]
    p = chunk_points[h, n]
    for a in range(3):
        s = 0.0
        for u in range(chunk_joints.shape[1]):
            w = chunk_weights[h, n, u]
            if w != 0.0:
                m = blend[t, chunk_joints[h, u], a]
                s += w * (m[0] * p[0] + m[1] * p[1] + m[2] * p[2] + m[3])
        x[a] = s - transforms[t, jb, a, 3]


@njit(cache=True, nogil=True)
def depths(transforms: np.ndarray, rest_inverse: np.ndarray, part_joints: np.ndarray,
           chunk_joints: np.ndarray, chunk_weights: np.ndarray, chunk_points: np.ndarray,
           t: np.ndarray, h: np.ndarray, n: np.ndarray, b: np.ndarray,
           planes: np.ndarray) -> np.ndarray:
    """Signed depth (Q,) of each selected point behind its plane (n, d) in part b's frame:
    −(n·R_bᵀ(p − t_b)) − d, p the linear-blend-skinned point (float64)."""
    return depths_blended(_blend(transforms, rest_inverse), transforms, part_joints,
                          chunk_joints, chunk_weights, chunk_points, t, h, n, b, planes)


@njit(cache=True, nogil=True)
def depths_blended(blend: np.ndarray, transforms: np.ndarray, part_joints: np.ndarray,
                   chunk_joints: np.ndarray, chunk_weights: np.ndarray, chunk_points: np.ndarray,
                   t: np.ndarray, h: np.ndarray, n: np.ndarray, b: np.ndarray,
                   planes: np.ndarray) -> np.ndarray:
    """`depths` from the skinning transforms `blend` (T,J,3,4) of `transforms` (`_blend`,
    `blend_at`), computed once by a caller that needs them again (`depths_backward_blended`)."""
    out = np.empty(len(t))
    x = np.empty(3)
    for i in range(len(t)):
        _depth_terms(blend, transforms, part_joints, chunk_joints, chunk_weights, chunk_points,
                     t[i], h[i], n[i], b[i], x)
        r = transforms[t[i], part_joints[b[i]]]
        s = 0.0
        for c in range(3):
            s += planes[i, c] * (x[0] * r[0, c] + x[1] * r[1, c] + x[2] * r[2, c])
        out[i] = -s - planes[i, 3]
    return out


@njit(cache=True, nogil=True)
def depths_backward(transforms: np.ndarray, rest_inverse: np.ndarray, part_joints: np.ndarray,
                    chunk_joints: np.ndarray, chunk_weights: np.ndarray,
                    chunk_points: np.ndarray, t: np.ndarray, h: np.ndarray, n: np.ndarray,
                    b: np.ndarray, planes: np.ndarray, grad: np.ndarray) -> np.ndarray:
    """∂/∂transforms (T,J,4,4) of Σ_i grad_i · depths_i (the bottom rows stay 0).

    With q = Rᵀx, x = p − t_b, p = Σ_u w_u B_u [v; 1], B_u = A_u[:3] Rinv_u:
    ∂q = −g n, ∂x = R ∂q, ∂R += x ∂qᵀ, ∂t_b −= ∂x, ∂B_u += w_u ∂x [v; 1]ᵀ, ∂A_u = ∂B_u Rinvᵀ."""
    return depths_backward_blended(_blend(transforms, rest_inverse), transforms, rest_inverse,
                                   part_joints, chunk_joints, chunk_weights, chunk_points, t, h,
                                   n, b, planes, grad)


@njit(cache=True, nogil=True)
def depths_backward_blended(blend: np.ndarray, transforms: np.ndarray, rest_inverse: np.ndarray,
                            part_joints: np.ndarray, chunk_joints: np.ndarray,
                            chunk_weights: np.ndarray, chunk_points: np.ndarray, t: np.ndarray,
                            h: np.ndarray, n: np.ndarray, b: np.ndarray, planes: np.ndarray,
                            grad: np.ndarray) -> np.ndarray:
    """`depths_backward` from the skinning transforms `blend` (`depths_blended`). Only the
    (frame, joint) skinning transforms a point reached are taken back through Rinv (the
    others' gradient is 0: adding it changed no bit)."""
    n_t, n_j = transforms.shape[0], transforms.shape[1]
    g_blend = np.zeros((n_t, n_j, 3, 4))
    touched = np.zeros((n_t, n_j), dtype=np.bool_)
    out = np.zeros((n_t, n_j, 4, 4))
    x = np.empty(3)
    dq = np.empty(3)
    dx = np.empty(3)
    for i in range(len(t)):
        if grad[i] == 0.0:
            continue
        ti, hi, ni = t[i], h[i], n[i]
        jb = part_joints[b[i]]
        _depth_terms(blend, transforms, part_joints, chunk_joints, chunk_weights, chunk_points,
                     ti, hi, ni, b[i], x)
        r = transforms[ti, jb]
        for c in range(3):
            dq[c] = -grad[i] * planes[i, c]
        for a in range(3):
            dx[a] = r[a, 0] * dq[0] + r[a, 1] * dq[1] + r[a, 2] * dq[2]
            for c in range(3):
                out[ti, jb, a, c] += x[a] * dq[c]
            out[ti, jb, a, 3] -= dx[a]
        p = chunk_points[hi, ni]
        for u in range(chunk_joints.shape[1]):
            w = chunk_weights[hi, ni, u]
            if w != 0.0:
                j = chunk_joints[hi, u]
                touched[ti, j] = True
                for a in range(3):
                    wa = w * dx[a]
                    g_blend[ti, j, a, 0] += wa * p[0]
                    g_blend[ti, j, a, 1] += wa * p[1]
                    g_blend[ti, j, a, 2] += wa * p[2]
                    g_blend[ti, j, a, 3] += wa
    for ti in range(n_t):
        for j in range(n_j):
            if not touched[ti, j]:
                continue
            for a in range(3):
                for c in range(4):
                    out[ti, j, a, c] += (g_blend[ti, j, a, 0] * rest_inverse[j, c, 0]
                                         + g_blend[ti, j, a, 1] * rest_inverse[j, c, 1]
                                         + g_blend[ti, j, a, 2] * rest_inverse[j, c, 2]
                                         + g_blend[ti, j, a, 3] * rest_inverse[j, c, 3])
    return out


class PointDepths(torch.autograd.Function):
    """`energy.point_depths` as one compiled forward and a hand-written backward (CPU).

    Why: the autograd graph of the per-point gathers and the (R,1,U)@(R,U,12) skinning
    product was most of the optimiser's backward; here the gradient of each depth is
    accumulated straight into the joint transforms'. Float64 inside: the depths agree with
    the torch ones to float32 rounding (tests: values, and gradcheck in float64)."""

    @staticmethod
    def forward(ctx, transforms: torch.Tensor, arrays: tuple) -> torch.Tensor:
        tr = transforms.detach().double().contiguous().numpy()
        ctx.tr, ctx.arrays = tr, arrays
        return torch.from_numpy(depths(tr, *arrays)).to(transforms.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        g = depths_backward(ctx.tr, *ctx.arrays, grad.detach().double().contiguous().numpy())
        return torch.from_numpy(g).to(grad.dtype), None
