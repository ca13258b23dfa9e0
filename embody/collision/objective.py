"""Adam's collision objective and its gradient by hand, with no autograd graph (CPU).

Why: once FK, the point depths and the capsules were compiled with hand-written gradients,
the torch glue between them (the blend of u into the pose, the pose's axis-angle gather, the
relu², the per-frame sums, the λ weighting, closeness and smoothness, and each op's autograd
node) was about half of an Adam step. Here a step is the compiled FK, the selection, the
depths and capsules, then their backward kernels chained by hand:

    obj = Σ_t λ_t e_t / T + λ_close Σ δ² / T + λ_smooth Σ (Δ²x)² / T,
    x = x0 + δ, δ = w ⊙ scatter(u),  e_t = live_t (Σ_i relu(d_i − τ)² + c Σ_pairs over²),

∂e/∂d_i = 2 relu(d_i − τ), then `narrow.depths_backward` and the capsules' pass give
∂/∂transforms, `compiled_fk`'s kernels ∂/∂axis-angle, and ∂/∂u = w ⊙ (∂/∂x + 2 λ_close δ / T)
gathered on the masked joints. The values are the autograd path's (same kernels, same float32
casts); gradients agree to float32 rounding (`tests/test_collision_objective.py`, float64 and
float32 against autograd through `optimize`'s objective).

Only the masked joints move, so the FK joints outside their subtree (`compiled_fk.subtree`:
spine, legs, head), their skinning transforms and every unmasked pose row are computed once;
each step redoes the subtree's rotations, world and skinning transforms and chains the backward
through the subtree only, in two compiled calls (`_forward_step`, `_gradient_step`) instead of
~25 tensor ops and conversions. The arithmetic per value is the one it replaced, so the same
bits (`tests/test_collision_objective.py`).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from embody.body.compiled_fk import (_rodrigues, backward_at, forward_at, rodrigues_at,
                                     rodrigues_backward_frames, subtree)
from embody.collision.capsules import Capsules, _capsule_pass
from embody.collision.energy import CollisionModel, Contacts, penetrations
from embody.collision.narrow import blend_at, depths_backward_blended, depths_blended


@njit(cache=True, nogil=True)
def _forward_step(x0: np.ndarray, u: np.ndarray, w: np.ndarray, jidx: np.ndarray,
                  source: np.ndarray, moved: np.ndarray, sub: np.ndarray, offsets: np.ndarray,
                  root: np.ndarray, parents: np.ndarray, rest_inverse: np.ndarray,
                  delta: np.ndarray, x: np.ndarray, aa: np.ndarray, coefficients: np.ndarray,
                  local: np.ndarray, world: np.ndarray, tr: np.ndarray, tr64: np.ndarray,
                  blend: np.ndarray) -> None:
    """δ = w ⊙ scatter(u), x = x0 + δ on the masked rows (in x's dtype, as the tensor ops),
    then the moved joints' rotations and the subtree's world transforms, their cast to x's
    dtype (`tr`) and back to float64 (`tr64`, what the depths see) and skinning transforms."""
    for t in range(u.shape[0]):
        for k in range(len(jidx)):
            j = jidx[k]
            for c in range(3):
                d = u[t, k, c] * w[t]
                delta[t, j, c] = d
                x[t, j, c] = x0[t, j, c] + d
        for j in moved:
            for c in range(3):
                aa[t, j, c] = np.float64(x[t, source[j], c])
    rodrigues_at(aa, moved, local, coefficients)
    forward_at(local, offsets, root, parents, sub, world)
    for t in range(world.shape[0]):
        for j in sub:
            for a in range(4):
                for c in range(4):
                    tr[t, j, a, c] = world[t, j, a, c]
                    tr64[t, j, a, c] = np.float64(tr[t, j, a, c])
    blend_at(tr64, rest_inverse, sub, blend)


@njit(cache=True, nogil=True)
def _moving_frames(g_tr: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """The frames with a non-zero ∂/∂world on one of `joints`: the others' ∂/∂axis-angle is
    0 (a zero gradient's chain adds only zeros to the closeness and smoothness terms)."""
    out = np.empty(g_tr.shape[0], dtype=np.int64)
    n = 0
    for t in range(g_tr.shape[0]):
        hit = False
        for j in joints:
            for a in range(3):
                for c in range(4):
                    if g_tr[t, j, a, c] != 0.0:
                        hit = True
            if hit:
                break
        if hit:
            out[n] = t
            n += 1
    return out[:n]


@njit(cache=True, nogil=True)
def _gradient_step(g_aa: np.ndarray, frames: np.ndarray, row_ptr: np.ndarray,
                   row_joints: np.ndarray, jidx: np.ndarray, s2: np.ndarray, delta: np.ndarray,
                   w: np.ndarray, c_smooth: float, c_close: float, out: np.ndarray) -> None:
    """∂/∂u (T,K,3) from ∂/∂axis-angle of the moved FK joints at `frames` (0 elsewhere;
    `row_joints[row_ptr[k]:…]`: those reading masked row k, summed in joint order as
    `index_add_`), the smoothness term (c_smooth Δ²x, added as +[t−2] −2[t−1] +[t]) and the
    closeness term (c_close δ), times w."""
    n_t = out.shape[0]
    live = np.zeros(n_t, dtype=np.bool_)
    live[frames] = True
    for t in range(n_t):
        for k in range(len(jidx)):
            j = jidx[k]
            for c in range(3):
                g = 0.0
                if live[t]:
                    for m in range(row_ptr[k], row_ptr[k + 1]):
                        g += g_aa[t, row_joints[m], c]
                if t >= 2:
                    g = g + c_smooth * np.float64(s2[t - 2, j, c])
                if 1 <= t <= n_t - 2:
                    g = g - 2.0 * (c_smooth * np.float64(s2[t - 1, j, c]))
                if t <= n_t - 3:
                    g = g + c_smooth * np.float64(s2[t, j, c])
                g = g + c_close * np.float64(delta[t, j, c])
                out[t, k, c] = g * np.float64(w[t])


class Objective:
    """The objective of `optimize._optimise` over u (T,K,3) for fixed x0, w and weights, in
    three calls per step as the optimiser needs them: `pose(u)` (FK: the transforms the broad
    phase refreshes on), `energies(near, ...)` (e_t, and the clear test's exact energies that
    set λ), `gradient(lam)` (the objective and ∂/∂u)."""

    def __init__(self, fk: tuple[np.ndarray, ...], model: CollisionModel, x0: torch.Tensor,
                 w: torch.Tensor, jidx: torch.Tensor, live: torch.Tensor,
                 caps: Capsules | None, capsule_weight: float, lambda_close: float,
                 lambda_smooth: float) -> None:
        self.source, self.offsets, self.root, self.parents, self.order = fk
        self.model, self.x0, self.w, self.jidx, self.live = model, x0, w, jidx, live
        self.caps = caps if caps is not None and len(caps.reach) else None
        self.cw, self.lc, self.ls = capsule_weight, lambda_close, lambda_smooth
        jn = jidx.numpy().astype(np.int64)
        self.jn = jn
        # the FK joints whose axis-angle is a masked pose row (the only rows ∂/∂u reads) and
        # every joint they move: the rest of the FK is the input's, computed here once
        self.moved = np.flatnonzero(np.isin(self.source, jn)).astype(np.int64)
        self.sub = subtree(self.parents, self.order, self.moved)
        self.row_joints, self.row_ptr = self._row_lists(jn)
        self.arrays = (model.part_joints, model.chunk_joints, model.chunk_weights,
                       model.chunk_points)
        with torch.no_grad():  # unmasked rows: δ = 0·w = 0, x = x0 + 0 (as the tensor ops)
            self.x0_np = x0.detach().contiguous().numpy()
            self.w_np = w.detach().reshape(-1).contiguous().numpy()
            self.delta_np = np.zeros(self.x0_np.shape, dtype=self.x0_np.dtype)
            self.x_np = (x0 + torch.zeros_like(x0)).contiguous().numpy().copy()
        self.delta, self.x = torch.from_numpy(self.delta_np), torch.from_numpy(self.x_np)
        t, n_j = x0.shape[0], len(self.source)
        pad = np.zeros((t, x0.shape[1] + 1, 3))
        pad[:, :-1] = self.x_np
        self.aa = np.ascontiguousarray(pad[:, self.source])
        self.local = np.empty((t, n_j, 3, 3))
        _rodrigues(self.aa, self.local)
        self.world = np.empty((t, n_j, 4, 4))
        forward_at(self.local, self.offsets, self.root, self.parents, self.order, self.world)
        self.tr_np = self.world.astype(self.x_np.dtype)
        self.tr64 = self.tr_np.astype(np.float64)
        self.tr = torch.from_numpy(self.tr_np)
        self.blend = np.zeros((t, n_j, 3, 4))
        blend_at(self.tr64, model.rest_inverse, np.arange(n_j), self.blend)
        self.g_local = np.zeros((t, n_j, 3, 3))
        self.g_aa = np.zeros((t, n_j, 3))
        self.coefficients = np.zeros((t, n_j, 2))

    def _row_lists(self, jn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(joints, ptr): the moved FK joints reading each masked row, in joint order."""
        joints: list[int] = []
        ptr = [0]
        for r in jn:
            joints.extend(int(j) for j in self.moved if self.source[j] == r)
            ptr.append(len(joints))
        return np.asarray(joints, dtype=np.int64), np.asarray(ptr, dtype=np.int64)

    @torch.no_grad()
    def pose(self, u: torch.Tensor) -> torch.Tensor:
        """δ, x and the joint transforms (T,J,4,4) (x's dtype, as `joint_transforms_compiled`).
        The returned tensor is this objective's buffer: the next call overwrites it."""
        _forward_step(self.x0_np, u.detach().numpy(), self.w_np, self.jn, self.source,
                      self.moved, self.sub, self.offsets, self.root, self.parents,
                      self.model.rest_inverse, self.delta_np, self.x_np, self.aa,
                      self.coefficients, self.local, self.world, self.tr_np, self.tr64,
                      self.blend)
        return self.tr

    @torch.no_grad()
    def energies(self, near: Contacts, tolerance: float, exact_tolerance: float | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """e_t (T,) at `tolerance` (live frames, capsules included) and, with
        `exact_tolerance`, the exact energies there (live frames, no capsules), as
        `energy.frame_energies_and_exact`."""
        t, dtype = self.tr.shape[0], self.tr.dtype
        e = self.tr.new_zeros(t)
        exact = None if exact_tolerance is None else self.tr.new_zeros(t)
        self.sel = sel = penetrations(self.model, self.tr, tolerance, near)
        if sel is not None:
            self.rows = (sel.t.numpy(), sel.h.numpy(), sel.n.numpy(), sel.b.numpy(),
                         sel.plane.detach().double().numpy())
            signed = torch.from_numpy(depths_blended(self.blend, self.tr64, *self.arrays,
                                                     *self.rows)).to(dtype)
            self.depth = torch.relu(signed - tolerance)
            e = e.index_add(0, sel.t, self.depth * self.depth)
            if exact is not None:
                inside = torch.nonzero(sel.f < -exact_tolerance).squeeze(1)
                deep = torch.relu(signed[inside] - exact_tolerance)
                exact = exact.index_add(0, sel.t[inside], deep * deep)
        e = e * self.live
        exact = None if exact is None else exact * self.live
        if self.caps is not None:
            self.pos = np.ascontiguousarray(self.tr64[:, :, :3, 3])
            c = self.caps
            ce = _capsule_pass(self.pos, c.a, c.b, c.reach, 0.0, np.empty(0),
                               np.empty((0, 0, 3)))
            e = e + self.cw * torch.from_numpy(ce).to(dtype) * self.live
        self.e = e
        return e, exact

    @torch.no_grad()
    def gradient(self, lam: torch.Tensor, value: bool = True) -> tuple[float, torch.Tensor]:
        """The objective with per-frame weights `lam` (0.0 unless `value`: the optimiser reads
        it at its refresh steps only) and its gradient in u (T,K,3)."""
        t, x, delta = self.x.shape[0], self.x, self.delta
        s2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
        obj = 0.0 if not value else (lam * self.e).sum() / t \
            + self.lc * ((delta ** 2).sum() / t) + self.ls * ((s2 ** 2).sum() / t)
        g_e = (lam / t * self.live).double()  # ∂obj/∂e_t, through live
        if self.sel is not None:
            g_d = (g_e[self.sel.t] * 2.0 * self.depth.double()).numpy()
            g_tr = depths_backward_blended(self.blend, self.tr64, self.model.rest_inverse,
                                           *self.arrays, *self.rows, g_d)
        else:
            g_tr = np.zeros(self.tr64.shape)
        if self.caps is not None:
            c = self.caps
            g_pos = np.zeros(self.pos.shape)
            _capsule_pass(self.pos, c.a, c.b, c.reach, 0.0, (g_e * self.cw).numpy(), g_pos)
            g_tr[:, :, :3, 3] += g_pos
        frames = _moving_frames(g_tr, self.sub)
        backward_at(self.local, self.world, self.offsets, self.parents, self.sub, g_tr, frames,
                    self.g_local)
        rodrigues_backward_frames(self.aa, self.coefficients, self.g_local, frames, self.moved,
                                  self.g_aa)
        grad = np.empty((t, len(self.jn), 3), dtype=self.x_np.dtype)
        _gradient_step(self.g_aa, frames, self.row_ptr, self.row_joints, self.jn,
                       s2.contiguous().numpy(), self.delta_np, self.w_np, 2.0 * self.ls / t,
                       2.0 * self.lc / t, grad)
        return float(obj), torch.from_numpy(grad)
