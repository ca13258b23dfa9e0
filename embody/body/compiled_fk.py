"""Forward kinematics (axis-angle → world transforms) with a hand-written gradient, compiled
(numba): `compiled_fk`.

Why: the collision optimiser runs FK and its backward every Adam step on every frame of the
window, and in torch that is ~90 small tensor ops a level-by-level pass forward and as many
autograd nodes back (~7 ms for 180 frames, ~40 % of a step after the energy was compiled).
Here both are one loop over frames and joints: Rodrigues' formula as
`rotations.axis_angle_to_matrix` writes it (its series near 0), then the forward of
`kinematics.forward_kinematics`
(world R_j = R_p L_j, p_j = p_p + R_p o_j), the backward by reverse accumulation down the
tree (children first):

    ∂L_j = R_pᵀ ∂R_j,   ∂R_p += ∂R_j L_jᵀ + ∂p_j o_jᵀ,   ∂p_p += ∂p_j.

Differentiable in the axis-angles only (the bone offsets and the root position are
treated as constants: the optimiser moves joint rotations). Arithmetic is float64 inside, so
the values agree with the torch FK to the input dtype's rounding, not bit for bit
(`tests/test_compiled_fk.py`: values, and gradcheck in float64).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit


@njit(cache=True, nogil=True)
def forward_at(local: np.ndarray, offsets: np.ndarray, root: np.ndarray, parents: np.ndarray,
               order: np.ndarray, out: np.ndarray) -> None:
    """World transforms `out` (T,J,4,4) of the joints in `order` (parents first) from their
    local rotations (T,J,3,3); a joint whose parent is not in `order` reads the parent's world
    transform already in `out`. With `subtree`'s order this redoes only the joints a few
    moved rotations reach (the same arithmetic per joint as the whole pass, so the same
    bits)."""
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
def backward_at(local: np.ndarray, world: np.ndarray, offsets: np.ndarray, parents: np.ndarray,
                order: np.ndarray, grad: np.ndarray, frames: np.ndarray, out: np.ndarray) -> None:
    """`out` (T,J,3,3) ∂/∂local of the joints in `order` at `frames` from `grad` (T,J,4,4)
    ∂/∂world (its bottom row unused). `order` must hold every descendant of its joints
    (`subtree`): a joint's ∂local reads its descendants' ∂world only; the other joints' and
    frames' `out` is left as is."""
    n_j = local.shape[1]
    g_r = np.empty((n_j, 3, 3))
    g_p = np.empty((n_j, 3))
    inside = np.zeros(n_j, dtype=np.bool_)
    for j in order:
        inside[j] = True
    for t in frames:
        o = offsets[t] if offsets.shape[0] > 1 else offsets[0]
        for j in order:
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
            if not inside[p]:  # the parent's gradient is not asked for
                continue
            for a in range(3):
                for b in range(3):
                    g_r[p, a, b] += (g_r[j, a, 0] * local[t, j, b, 0]
                                     + g_r[j, a, 1] * local[t, j, b, 1]
                                     + g_r[j, a, 2] * local[t, j, b, 2]
                                     + g_p[j, a] * o[j, b])
                g_p[p, a] += g_p[j, a]


#: Below this squared angle the series of `rotations.axis_angle_to_matrix` are used.
_SMALL = 1e-6


@njit(cache=True, nogil=True)
def _coefficients(s: float) -> tuple[float, float, float, float]:
    """a = sin θ/θ, b = (1 − cos θ)/θ² and their derivatives in s = θ² (the series of
    `rotations.axis_angle_to_matrix` below `_SMALL`)."""
    if s < _SMALL:
        return (1.0 - s / 6.0 + s * s / 120.0, 0.5 - s / 24.0 + s * s / 720.0,
                -1.0 / 6.0 + s / 60.0, -1.0 / 24.0 + s / 360.0)
    theta = np.sqrt(s)
    a = np.sin(theta) / theta
    half = np.sin(0.5 * theta)
    b = 2.0 * half * half / s
    return a, b, (np.cos(theta) - a) / (2.0 * s), (0.5 * a - b) / s


@njit(cache=True, nogil=True, inline="always")
def _values(s: float) -> tuple[float, float]:
    """a and b of `_coefficients` (the same arithmetic) without the derivatives' cosine."""
    if s < _SMALL:
        return 1.0 - s / 6.0 + s * s / 120.0, 0.5 - s / 24.0 + s * s / 720.0
    theta = np.sqrt(s)
    half = np.sin(0.5 * theta)
    return np.sin(theta) / theta, 2.0 * half * half / s


@njit(cache=True, nogil=True, inline="always")
def _derivatives(s: float, a: float, b: float) -> tuple[float, float]:
    """The derivatives of `_coefficients` (the same arithmetic) from its a and b."""
    if s < _SMALL:
        return -1.0 / 6.0 + s / 60.0, -1.0 / 24.0 + s / 360.0
    return (np.cos(np.sqrt(s)) - a) / (2.0 * s), (0.5 * a - b) / s


@njit(cache=True, nogil=True)
def _rodrigues(axis_angle: np.ndarray, out: np.ndarray) -> None:
    """R = (1 − bθ²) I + a K + b r rᵀ per (T,J) axis-angle (3,), as `axis_angle_to_matrix`."""
    for t in range(axis_angle.shape[0]):
        for j in range(axis_angle.shape[1]):
            _rodrigues_one(axis_angle[t, j], out[t, j])


@njit(cache=True, nogil=True)
def rodrigues_at(axis_angle: np.ndarray, joints: np.ndarray, out: np.ndarray,
                 coefficients: np.ndarray) -> None:
    """`_rodrigues` of the given joints only (`out`'s other entries untouched), keeping each
    one's a and b of `_coefficients` in `coefficients` (T,J,2) for
    `rodrigues_backward_frames` (which derives the derivatives where it needs them)."""
    for t in range(axis_angle.shape[0]):
        for j in joints:
            c = coefficients[t, j]
            v = axis_angle[t, j]
            c[0], c[1] = _values(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            _rodrigues_from(v, c[0], c[1], out[t, j])


@njit(cache=True, nogil=True, inline="always")
def _rodrigues_one(v: np.ndarray, r: np.ndarray) -> None:
    a, b, _, _ = _coefficients(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    _rodrigues_from(v, a, b, r)


@njit(cache=True, nogil=True, inline="always")
def _rodrigues_from(v: np.ndarray, a: float, b: float, r: np.ndarray) -> None:
    x, y, z = v[0], v[1], v[2]
    s = x * x + y * y + z * z
    c = 1.0 - b * s
    r[0, 0], r[0, 1], r[0, 2] = c + b * x * x, -a * z + b * x * y, a * y + b * x * z
    r[1, 0], r[1, 1], r[1, 2] = a * z + b * y * x, c + b * y * y, -a * x + b * y * z
    r[2, 0], r[2, 1], r[2, 2] = -a * y + b * z * x, a * x + b * z * y, c + b * z * z


@njit(cache=True, nogil=True, inline="always")
def _rodrigues_backward_one(r: np.ndarray, g: np.ndarray, out: np.ndarray) -> None:
    a, b, da, db = _coefficients(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    _rodrigues_backward_from(r, a, b, da, db, g, out)


@njit(cache=True, nogil=True, inline="always")
def _rodrigues_backward_from(r: np.ndarray, a: float, b: float, da: float, db: float,
                             g: np.ndarray, out: np.ndarray) -> None:
    x, y, z = r[0], r[1], r[2]
    s = x * x + y * y + z * z
    trace = g[0, 0] + g[1, 1] + g[2, 2]
    gk = (g[2, 1] - g[1, 2]) * x + (g[0, 2] - g[2, 0]) * y + (g[1, 0] - g[0, 1]) * z
    rgr = 0.0
    for i in range(3):
        for k in range(3):
            rgr += r[i] * g[i, k] * r[k]
    common = 2.0 * (-(b + db * s) * trace + da * gk + db * rgr)
    dk = (g[2, 1] - g[1, 2], g[0, 2] - g[2, 0], g[1, 0] - g[0, 1])
    for k in range(3):
        sym = 0.0
        for i in range(3):
            sym += (g[k, i] + g[i, k]) * r[i]
        out[k] = common * r[k] + a * dk[k] + b * sym


@njit(cache=True, nogil=True)
def _rodrigues_backward(axis_angle: np.ndarray, grad: np.ndarray, out: np.ndarray) -> None:
    """∂/∂r (T,J,3) from ∂/∂R (T,J,3,3): with s = r·r,
    ∂r_k = −2(b + b′s) tr G r_k + 2a′(G:K) r_k + a (G:∂K/∂r_k) + 2b′(rᵀGr) r_k + b (Gr + Gᵀr)_k."""
    for t in range(axis_angle.shape[0]):
        for j in range(axis_angle.shape[1]):
            _rodrigues_backward_one(axis_angle[t, j], grad[t, j], out[t, j])


@njit(cache=True, nogil=True)
def rodrigues_backward_at(axis_angle: np.ndarray, grad: np.ndarray, joints: np.ndarray,
                          out: np.ndarray) -> None:
    """`_rodrigues_backward` of the given joints only (`out`'s other entries untouched): a
    caller that needs the gradient of a few joints (the collision optimiser's masked ones)
    skips the others' work; the same arithmetic per joint."""
    for t in range(axis_angle.shape[0]):
        for j in joints:
            _rodrigues_backward_one(axis_angle[t, j], grad[t, j], out[t, j])


@njit(cache=True, nogil=True)
def rodrigues_backward_frames(axis_angle: np.ndarray, coefficients: np.ndarray,
                              grad: np.ndarray, frames: np.ndarray, joints: np.ndarray,
                              out: np.ndarray) -> None:
    """`rodrigues_backward_at` at `frames` only, from the `coefficients` `rodrigues_at` kept
    (the same values: no sine, cosine or root computed twice)."""
    for t in frames:
        for j in joints:
            c = coefficients[t, j]
            r = axis_angle[t, j]
            da, db = _derivatives(r[0] * r[0] + r[1] * r[1] + r[2] * r[2], c[0], c[1])
            _rodrigues_backward_from(r, c[0], c[1], da, db, grad[t, j], out[t, j])


class _CompiledFK(torch.autograd.Function):
    @staticmethod
    def forward(ctx, axis_angle: torch.Tensor, offsets: torch.Tensor, root: torch.Tensor,
                parents: np.ndarray, order: np.ndarray) -> torch.Tensor:
        aa = axis_angle.detach().double().contiguous().numpy()
        local = np.empty((*aa.shape[:2], 3, 3))
        _rodrigues(aa, local)
        off = offsets.detach().double().reshape(-1, *offsets.shape[-2:]).numpy()
        world = np.empty((*aa.shape[:2], 4, 4))
        forward_at(local, off, root.detach().double().numpy(), parents, order, world)
        ctx.parents, ctx.order = parents, order
        ctx.aa, ctx.local, ctx.off, ctx.world = aa, local, off, world
        return torch.from_numpy(world).to(axis_angle.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        g_local = np.empty(ctx.local.shape)
        backward_at(ctx.local, ctx.world, ctx.off, ctx.parents, ctx.order,
                    grad.detach().double().contiguous().numpy(), np.arange(len(g_local)),
                    g_local)
        out = np.empty(ctx.aa.shape)
        _rodrigues_backward(ctx.aa, g_local, out)
        return torch.from_numpy(out).to(grad.dtype), None, None, None, None


def subtree(parents: np.ndarray, order: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """`order` (parents first) restricted to `joints` and all their descendants: the joints
    whose world transform moves when only `joints`' rotations change (`forward_at`,
    `backward_at`)."""
    inside = np.zeros(len(parents), dtype=bool)
    inside[np.asarray(joints, dtype=np.int64)] = True
    for j in order:
        if parents[j] >= 0 and inside[parents[j]]:
            inside[j] = True
    return np.asarray(order)[inside[np.asarray(order)]].astype(np.int64)


def compiled_fk(axis_angle: torch.Tensor, offsets: torch.Tensor, root: torch.Tensor,
                parents: np.ndarray, levels: list[np.ndarray]) -> torch.Tensor:
    """`kinematics.forward_kinematics` of `rotations.axis_angle_to_matrix(axis_angle)` (T,J,3)
    on the CPU, compiled, differentiable in `axis_angle` only (offsets and root must not
    require gradients)."""
    if offsets.requires_grad or root.requires_grad or axis_angle.device.type != "cpu":
        raise ValueError("compiled_fk: CPU only, differentiable in axis_angle only")
    order = np.concatenate([np.flatnonzero(np.asarray(parents) < 0), *levels]).astype(np.int64)
    t = axis_angle.shape[0]
    return _CompiledFK.apply(axis_angle, offsets, root.expand(t, 3).contiguous(),
                             np.asarray(parents, dtype=np.int64), order)
