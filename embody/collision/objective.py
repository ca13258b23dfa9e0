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
"""

from __future__ import annotations

import numpy as np
import torch

from embody.body.compiled_fk import _backward, _forward, _rodrigues, rodrigues_backward_at
from embody.collision.capsules import Capsules, _capsule_pass
from embody.collision.energy import CollisionModel, Contacts, penetrations
from embody.collision.narrow import depths, depths_backward


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
        self.pad: np.ndarray | None = None  # the pose with the zero row the source indexes
        self.source_t = torch.as_tensor(self.source)
        # the FK joints whose axis-angle is a masked pose row (the only rows ∂/∂u reads)
        self.moved = np.flatnonzero(np.isin(self.source, jidx.numpy())).astype(np.int64)
        self.arrays = (model.rest_inverse, model.part_joints, model.chunk_joints,
                       model.chunk_weights, model.chunk_points)

    @torch.no_grad()
    def pose(self, u: torch.Tensor) -> torch.Tensor:
        """δ, x and the joint transforms (T,J,4,4) (float32, as `joint_transforms_compiled`)."""
        self.delta = torch.zeros_like(self.x0).index_copy(1, self.jidx, u) * self.w
        self.x = self.x0 + self.delta
        if self.pad is None:
            self.pad = np.zeros((self.x.shape[0], self.x.shape[1] + 1, 3))
        self.pad[:, :-1] = self.x.numpy()  # float32 → float64 is exact
        self.aa = self.pad[:, self.source]
        self.local = np.empty((*self.aa.shape[:2], 3, 3))
        _rodrigues(self.aa, self.local)
        self.world = np.empty((*self.aa.shape[:2], 4, 4))
        _forward(self.local, self.offsets, self.root, self.parents, self.order, self.world)
        self.tr = torch.from_numpy(self.world).to(self.x.dtype)
        self.tr64 = self.tr.double().numpy()  # what the depths and capsules see
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
            signed = torch.from_numpy(depths(self.tr64, *self.arrays, *self.rows)).to(dtype)
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
    def gradient(self, lam: torch.Tensor) -> tuple[float, torch.Tensor]:
        """The objective with per-frame weights `lam` and its gradient in u (T,K,3)."""
        t, x, delta = self.x.shape[0], self.x, self.delta
        s2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
        obj = (lam * self.e).sum() / t + self.lc * ((delta ** 2).sum() / t) \
            + self.ls * ((s2 ** 2).sum() / t)
        g_e = (lam / t * self.live).double()  # ∂obj/∂e_t, through live
        if self.sel is not None:
            g_d = (g_e[self.sel.t] * 2.0 * self.depth.double()).numpy()
            g_tr = depths_backward(self.tr64, *self.arrays, *self.rows, g_d)
        else:
            g_tr = np.zeros(self.tr64.shape)
        if self.caps is not None:
            c = self.caps
            g_pos = np.zeros(self.pos.shape)
            _capsule_pass(self.pos, c.a, c.b, c.reach, 0.0, (g_e * self.cw).numpy(), g_pos)
            g_tr[:, :, :3, 3] += g_pos
        g_local = np.empty(self.local.shape)
        _backward(self.local, self.world, self.offsets, self.parents, self.order, g_tr, g_local)
        g_aa = np.zeros(self.aa.shape)  # only the masked joints' rows are read below
        rodrigues_backward_at(self.aa, g_local, self.moved, g_aa)
        g_pad = torch.zeros(t, x.shape[1] + 1, 3, dtype=torch.float64).index_add_(
            1, self.source_t, torch.from_numpy(g_aa))
        g_x = g_pad[:, :-1]
        g_s = (2.0 * self.ls / t) * s2.double()
        g_x[2:] += g_s
        g_x[1:-1] -= 2.0 * g_s
        g_x[:-2] += g_s
        g_delta = g_x + (2.0 * self.lc / t) * delta.double()
        grad = (g_delta * self.w.double()).index_select(1, self.jidx).to(x.dtype)
        return float(obj), grad
