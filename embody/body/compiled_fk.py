"""Forward kinematics with a hand-written gradient, compiled (numba): `compiled_fk`.

Why: the collision optimiser runs FK and its backward every Adam step on every frame of the
window, and in torch that is ~90 small tensor ops a level-by-level pass forward and as many
autograd nodes back (~7 ms for 180 frames, ~40 % of a step after the energy was compiled).
Here both are one loop over frames and joints: the forward of `kinematics.forward_kinematics`
(world R_j = R_p L_j, p_j = p_p + R_p o_j), the backward by reverse accumulation down the
tree (children first):

    ∂L_j = R_pᵀ ∂R_j,   ∂R_p += ∂R_j L_jᵀ + ∂p_j o_jᵀ,   ∂p_p += ∂p_j.

Differentiable in the local rotations only (the bone offsets and the root position are
treated as constants: the optimiser moves joint rotations). Arithmetic is float64 inside, so
the values agree with the torch FK to the input dtype's rounding, not bit for bit
(`tests/test_compiled_fk.py`: values, and gradcheck in float64).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit


@njit(cache=True, nogil=True)
def _forward(local: np.ndarray, offsets: np.ndarray, root: np.ndarray, parents: np.ndarray,
             order: np.ndarray, out: np.ndarray) -> None:
    n_t = local.shape[0]
    for t in range(n_t):
        o = offsets[t] if offsets.shape[0] > 1 else offsets[0]
        for j in order:
            p = parents[j]
            if p < 0:
                for a in range(3):
                    for b in range(3):
                        out[t, j, a, b] = local[t, j, a, b]
                    out[t, j, a, 3] = root[t, a]
            else:
                for a in range(3):
                    for b in range(3):
                        out[t, j, a, b] = (out[t, p, a, 0] * local[t, j, 0, b]
                                           + out[t, p, a, 1] * local[t, j, 1, b]
                                           + out[t, p, a, 2] * local[t, j, 2, b])
                    out[t, j, a, 3] = out[t, p, a, 3] + (out[t, p, a, 0] * o[j, 0]
                                                         + out[t, p, a, 1] * o[j, 1]
                                                         + out[t, p, a, 2] * o[j, 2])
            out[t, j, 3, 0] = out[t, j, 3, 1] = out[t, j, 3, 2] = 0.0
            out[t, j, 3, 3] = 1.0


@njit(cache=True, nogil=True)
def _backward(local: np.ndarray, world: np.ndarray, offsets: np.ndarray, parents: np.ndarray,
              order: np.ndarray, grad: np.ndarray, out: np.ndarray) -> None:
    """`out` (T,J,3,3) ∂/∂local from `grad` (T,J,4,4) ∂/∂world (its bottom row unused)."""
    n_t, n_j = local.shape[0], local.shape[1]
    g_r = np.empty((n_j, 3, 3))
    g_p = np.empty((n_j, 3))
    for t in range(n_t):
        o = offsets[t] if offsets.shape[0] > 1 else offsets[0]
        for j in range(n_j):
            for a in range(3):
                for b in range(3):
                    g_r[j, a, b] = grad[t, j, a, b]
                g_p[j, a] = grad[t, j, a, 3]
        for i in range(len(order) - 1, -1, -1):
            j = order[i]
            p = parents[j]
            if p < 0:
                for a in range(3):
                    for b in range(3):
                        out[t, j, a, b] = g_r[j, a, b]
                continue
            for a in range(3):
                for b in range(3):
                    out[t, j, a, b] = (world[t, p, 0, a] * g_r[j, 0, b]
                                       + world[t, p, 1, a] * g_r[j, 1, b]
                                       + world[t, p, 2, a] * g_r[j, 2, b])
            for a in range(3):
                for b in range(3):
                    g_r[p, a, b] += (g_r[j, a, 0] * local[t, j, b, 0]
                                     + g_r[j, a, 1] * local[t, j, b, 1]
                                     + g_r[j, a, 2] * local[t, j, b, 2]
                                     + g_p[j, a] * o[j, b])
                g_p[p, a] += g_p[j, a]


class _CompiledFK(torch.autograd.Function):
    @staticmethod
    def forward(ctx, local_rot: torch.Tensor, offsets: torch.Tensor, root: torch.Tensor,
                parents: np.ndarray, order: np.ndarray) -> torch.Tensor:
        local = local_rot.detach().double().numpy()
        off = offsets.detach().double().reshape(-1, *offsets.shape[-2:]).numpy()
        world = np.empty((*local.shape[:2], 4, 4))
        _forward(local, off, root.detach().double().numpy(), parents, order, world)
        ctx.parents, ctx.order = parents, order
        ctx.save_for_backward(local_rot, offsets)
        ctx.world = world
        return torch.from_numpy(world).to(local_rot.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        local_rot, offsets = ctx.saved_tensors
        local = local_rot.detach().double().numpy()
        off = offsets.detach().double().reshape(-1, *offsets.shape[-2:]).numpy()
        out = np.empty(local.shape)
        _backward(local, ctx.world, off, ctx.parents, ctx.order,
                  grad.detach().double().contiguous().numpy(), out)
        return torch.from_numpy(out).to(local_rot.dtype), None, None, None, None


def compiled_fk(local_rot: torch.Tensor, offsets: torch.Tensor, root: torch.Tensor,
                parents: np.ndarray, levels: list[np.ndarray]) -> torch.Tensor:
    """`kinematics.forward_kinematics` (same arguments) on the CPU, compiled, differentiable in
    `local_rot` only (offsets and root must not require gradients)."""
    if offsets.requires_grad or root.requires_grad or local_rot.is_cuda:
        raise ValueError("compiled_fk: CPU only, differentiable in local_rot only")
    order = np.concatenate([np.flatnonzero(np.asarray(parents) < 0), *levels]).astype(np.int64)
    t = local_rot.shape[0]
    return _CompiledFK.apply(local_rot, offsets, root.expand(t, 3).contiguous(),
                             np.asarray(parents, dtype=np.int64), order)
