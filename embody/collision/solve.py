"""Gauss-Newton / Levenberg-Marquardt solve of the masked mitigation objective (Eq. 2–3).

Same objective as the Adam path (`optimize._optimise`), written as a sum of squared residuals

    Σ_t λ_t/T [Σ_i depth_i² + w_cap Σ_p over_p²] + λ_close/T ‖w u‖² + λ_smooth/T ‖Δ²(x0 + w u)‖²

over the masked joints u of the frames near a penetration (x = x0 + w(t) u, w the blend
weights). Why: Adam needed hundreds of steps, each a full broad phase + autograd pass; a
second-order step converges in ~5–15 iterations.

- *Residual Jacobians are analytic* (no autograd): a rotation δ_k of joint k (in its own frame,
  after its local rotation) turns everything below k about the world axis G_k δ_k through its
  origin o_k, so a point's depth behind a plane of part b changes by
  G_kᵀ((c_b (p − o_k) − Σ_u w_u[u ⊑ k](p_u − o_k)) × n) · δ_k (c_b = 1 when b rides on k),
  and the axis-angle coordinates map to δ through the right Jacobian of SO(3).
- *Structure*: collision residuals couple the joints of one frame, closeness is diagonal and
  smoothness couples one coordinate over t ± 2, so the normal matrix ordered frame-major is
  banded (half-bandwidth 2P) and solved with a banded Cholesky (`scipy.linalg.solveh_banded`).
- *Cheap evaluations*: the broad phase runs on refreshes only; in between, the candidate
  (point, piece) pairs within `refresh_margin` are re-evaluated point by point (all planes of
  their piece, deepest piece per part), which is what the inner LM iterations need.
- λ continuation as in the Adam path: a frame's λ grows while it still penetrates beyond
  `tolerance`; the solve does not stop while any frame does (the iteration budget bounds it).

Status (opt-in, `collision.solver: gauss_newton`; measured on a loaded 2-core machine, 2026-11-23):
seq_002 of the default set is cleared in 7 iterations (mesh depth 15.9 → 0.0 mm, Pose MSE
0.00018, as Adam); seq_000 and seq_003 stall after ~10 iterations with 14 mm / 58 mm of
residual depth: there a forearm sits ~58 mm inside two torso parts at once (spine1 and
spine3), whose nearest-face pushes cancel (a saddle, like crossed forearms), and each
iteration still costs ~1 s of CPU (the per-point evaluation of ~20–60k near (point, part)
groups dominates, not the banded solve). Open: why those residuals stall, and a cheaper
evaluation (float32, fewer candidates) before this can replace Adam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.linalg import solve_triangular

from embody.body.base import BodyModel
from embody.collision.capsules import Capsules, segment_closest
from embody.collision.energy import CollisionModel, _blend, _box_distance, _to_part, contacts
from embody.config.collision import CollisionConfig
from embody.motion import JOINT_NAMES, Motion

import os
_DEBUG = bool(os.environ.get("EMBODY_SOLVE_DEBUG"))
#: SMPL-X pose index of the first finger joint (left_index1).
FIRST_FINGER = 25


def _descendants(parents: np.ndarray) -> np.ndarray:
    """(J,J) bool: desc[k, u] when joint u is k or below it."""
    n = len(parents)
    desc = np.eye(n, dtype=bool)
    for u in range(n):
        p = int(parents[u])
        while p >= 0:
            desc[p, u] = True
            p = int(parents[p])
    return desc


def right_jacobian(x: torch.Tensor) -> torch.Tensor:
    """J_r(θ) (...,3,3): exp(θ + dθ) ≈ exp(θ) exp(J_r(θ) dθ)."""
    th2 = (x * x).sum(-1)
    small = th2 < 1e-8
    safe = torch.where(small, torch.ones_like(th2), th2)
    th = safe.sqrt()
    a = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(th)) / safe)
    b = torch.where(small, 1.0 / 6.0 - th2 / 120.0, (th - torch.sin(th)) / (safe * th))
    z = torch.zeros_like(x[..., 0])
    k = torch.stack((z, -x[..., 2], x[..., 1], x[..., 2], z, -x[..., 0],
                     -x[..., 1], x[..., 0], z), -1).reshape(*x.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=x.dtype)
    return eye - a[..., None, None] * k + b[..., None, None] * (k @ k)


@dataclass
class _Candidates:
    """Point-piece pairs near contact: frame, chunk, point, part b, piece, (point, part) group."""

    t: torch.Tensor
    h: torch.Tensor
    n: torch.Tensor
    b: torch.Tensor
    k: torch.Tensor
    group: torch.Tensor
    n_groups: int


def _candidates(model: CollisionModel, transforms: torch.Tensor, margin: float) -> _Candidates:
    d = model.tensors(transforms.dtype, transforms.device)
    c = contacts(model, transforms, margin)
    empty = torch.zeros(0, dtype=torch.long)
    if c.t.numel() == 0:
        return _Candidates(empty, empty, empty, empty, empty, empty, 0)
    g = transforms[:, d["part_joints"]]
    rot, trans = g[..., :3, :3], g[..., :3, 3]
    from embody.collision.energy import _row_points
    q = _to_part(rot, trans, c.t, c.b, _row_points(d, _blend(d, transforms), c.t, c.h))
    inbox = (_box_distance(q, d["piece_box"][c.k][:, None]) <= margin) & d["chunk_mask"][c.h]
    r, n = torch.nonzero(inbox, as_tuple=True)
    planes = d["planes"][c.k[r]]
    f = ((planes[..., :3] @ q[r, n].unsqueeze(-1)).squeeze(-1) + planes[..., 3]).amax(-1)
    near = f < margin  # the piece's own distance bound, tighter than its box
    r, n = r[near], n[near]
    t, h, b, k = c.t[r], c.h[r], c.b[r], c.k[r]
    n_chunks, n_parts, size = d["chunk_part"].shape[0], d["part_radius"].shape[0], q.shape[1]
    key = ((t * n_chunks + h) * size + n) * n_parts + b
    uniq, group = torch.unique(key, return_inverse=True)
    return _Candidates(t, h, n, b, k, group, int(uniq.numel()))


@dataclass
class _Problem:
    body: BodyModel
    model: CollisionModel
    caps: Capsules | None
    cfg: CollisionConfig
    x0: torch.Tensor          # (t,55,3) float64
    w: torch.Tensor           # (t,) blend weights
    betas: torch.Tensor
    mask_pose: np.ndarray     # (K,) pose joint ids of the mask present in the body
    mask_body: np.ndarray     # (K,) their body joint ids
    desc: torch.Tensor        # (J,J) float
    jr: torch.Tensor | None = None  # (t,K,3,3) right Jacobians at the current pose

    def pose(self, u: torch.Tensor) -> torch.Tensor:
        x = self.x0.clone()
        x[:, self.mask_pose] += self.w[:, None, None] * u
        return x


def _point_terms(pb: _Problem, cand: _Candidates, transforms: torch.Tensor, x: torch.Tensor,
                 tol: float, jac: bool):
    """Deepest-piece depth per (point, part) group (G,) minus `tol`, its frame, and (G,K,3)
    d depth / d x over the mask joints (when `jac`)."""
    d = pb.model.tensors(transforms.dtype, transforms.device)
    blend = _blend(d, transforms)                                   # (T,J,3,4)
    cj = d["chunk_joints"][cand.h]                                  # (R,U)
    wts = d["chunk_weights"][cand.h, cand.n]                        # (R,U)
    v = d["chunk_points"][cand.h, cand.n]                           # (R,3)
    a = blend[cand.t[:, None], cj]                                  # (R,U,3,4)
    pu = (a[..., :3] @ v[:, None, :, None]).squeeze(-1) + a[..., 3]  # (R,U,3)
    p = (wts[..., None] * pu).sum(1)                                # (R,3)
    jb = d["part_joints"][cand.b]
    gb = transforms[cand.t, jb]
    q = ((p - gb[:, :3, 3])[:, None, :] @ gb[:, :3, :3]).squeeze(1)  # (R,3) part frame
    planes = d["planes"][cand.k]                                    # (R,F,4)
    f, arg = ((planes[..., :3] @ q[..., None]).squeeze(-1) + planes[..., 3]).max(-1)
    # a part's SDF is the min over its pieces: the deepest candidate row of each group
    gmin = torch.full((cand.n_groups,), float("inf"), dtype=f.dtype).scatter_reduce(
        0, cand.group, f, "amin")
    win = f <= gmin[cand.group]
    rows = torch.full((cand.n_groups,), len(f), dtype=torch.long).scatter_reduce(
        0, cand.group[win], torch.nonzero(win).squeeze(1), "amin")
    depth = -f[rows] - tol
    if not jac:
        return depth, cand.t[rows], None
    pos = depth > 0
    rows, depth = rows[pos], depth[pos]
    t = cand.t[rows]
    nrm = (gb[rows, :3, :3] @ planes[rows, arg[rows], :3, None]).squeeze(-1)  # (G,3) world
    p, pu, wts, cj, jb = p[rows], pu[rows], wts[rows], cj[rows], jb[rows]
    tf = transforms[t][:, pb.mask_body]                             # (G,K,4,4)
    o = tf[..., :3, 3]
    desc = pb.desc[pb.mask_body]                                    # (K,J)
    lever = (wts[:, None, :] * desc[:, cj].permute(1, 0, 2)) @ pu   # (G,K,3) Σ_u w_u[u⊑k] p_u
    ca = (wts[:, None, :] * desc[:, cj].permute(1, 0, 2)).sum(-1, keepdim=True)
    cb = desc[:, jb].T[..., None]                                   # (G,K,1)
    vec = torch.linalg.cross((cb - ca) * (p[:, None] - o) - (lever - ca * p[:, None]),
                             nrm[:, None].expand_as(o))
    dd = (vec[..., None, :] @ tf[..., :3, :3]).squeeze(-2)          # (G,K,3) d depth / dδ
    return depth, t, (dd[..., None, :] @ pb.jr[t]).squeeze(-2)


def _capsule_terms(pb: _Problem, transforms: torch.Tensor, x: torch.Tensor, jac: bool):
    caps = pb.caps
    pos = transforms[:, :, :3, 3]
    s, tt, ca, cb = segment_closest(pos[:, caps.a[:, 0]], pos[:, caps.a[:, 1]],
                                    pos[:, caps.b[:, 0]], pos[:, caps.b[:, 1]])
    gap = ca - cb
    dist = gap.norm(dim=-1).clamp(min=1e-9)
    over = torch.as_tensor(caps.reach, dtype=pos.dtype) - dist        # (T,P)
    fr, pr = torch.nonzero(over > 0, as_tuple=True)
    if not jac or fr.numel() == 0:
        return over[fr, pr], fr, None
    ghat = gap[fr, pr] / dist[fr, pr, None]
    tf = transforms[fr][:, pb.mask_body]
    o = tf[..., :3, 3]                                                # (Q,K,3)
    desc = pb.desc[pb.mask_body]                                      # (K,J)

    def lever(j0, j1, frac):
        e0 = desc[:, j0].T[..., None] * (pos[fr, j0][:, None] - o)
        e1 = desc[:, j1].T[..., None] * (pos[fr, j1][:, None] - o)
        return (1 - frac)[:, None, None] * e0 + frac[:, None, None] * e1

    a0, a1 = (torch.as_tensor(caps.a[:, i])[pr] for i in (0, 1))
    b0, b1 = (torch.as_tensor(caps.b[:, i])[pr] for i in (0, 1))
    sig = lever(b0, b1, tt[fr, pr]) - lever(a0, a1, s[fr, pr])
    vec = torch.linalg.cross(sig, ghat[:, None].expand_as(sig))
    dd = (tf[..., :3, :3].transpose(-1, -2) @ vec[..., None]).squeeze(-1)
    return over[fr, pr], fr, (dd[..., None, :] @ pb.jr[fr]).squeeze(-2)


def _smooth_ops(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """D2 diag(w) (t−2, t) as a dense matrix and its normal matrix (t, t)."""
    t = len(w)
    d2 = np.zeros((max(t - 2, 0), t))
    for i in range(t - 2):
        d2[i, i:i + 3] = (1.0, -2.0, 1.0)
    a = d2 * w[None, :]
    return a, a.T @ a


def solve(body: BodyModel, model: CollisionModel, motion: Motion, idx: np.ndarray,
          weight: np.ndarray, cfg: CollisionConfig,
          caps: Capsules | None) -> tuple[np.ndarray, int]:
    """LM over the masked joints of the frames with weight > 0; returns (pose, iterations)."""
    active = np.flatnonzero(weight > 0)
    lo, hi = int(active[0]), int(active[-1]) + 1
    names = list(body.joint_names)
    keep = [j for j in idx if JOINT_NAMES[j] in names]
    mask_pose = np.array(keep, dtype=np.int64)
    mask_body = np.array([names.index(JOINT_NAMES[j]) for j in keep], dtype=np.int64)
    dt = torch.float64
    pb = _Problem(body, model, caps if caps is not None and len(caps.reach) else None, cfg,
                  torch.as_tensor(motion.pose[lo:hi], dtype=dt),
                  torch.as_tensor(weight[lo:hi], dtype=dt),
                  torch.as_tensor(motion.betas, dtype=dt), mask_pose, mask_body,
                  torch.as_tensor(_descendants(np.asarray(body.parents)), dtype=dt))
    t, k = pb.x0.shape[0], len(mask_pose)
    wn = weight[lo:hi]
    live = wn > 0
    tol_opt = cfg.tolerance - cfg.clearance
    lam = np.full(t, float(cfg.lambda_col))
    lc, ls, cw = cfg.lambda_close / t, cfg.lambda_smooth / t, cfg.capsule_weight
    d2w, smooth_n = _smooth_ops(wn)
    x0m = pb.x0[:, mask_pose].numpy().reshape(t, -1)                 # (t, 3K)
    u = torch.zeros(t, k, 3, dtype=dt)
    variables = np.zeros(k, dtype=bool)
    # finger joints stay out of the solve when the mask also holds the arm chain: the arm
    # separates the parts and the banded system stays narrow (3 x 8 unknowns per frame; with
    # all 38 arm-mask joints one solve took seconds). Only joints that move a residual count.
    fingers = mask_pose >= FIRST_FINGER
    allowed = ~fingers if (~fingers).any() else fingers
    cand = None

    def evaluate(u_: torch.Tensor, jac: bool):
        x = pb.pose(u_)
        tr = body.joint_transforms(x, pb.betas)
        if jac:
            pb.jr = right_jacobian(x[:, pb.mask_pose])
        dep, ft, jd = _point_terms(pb, cand, tr, x, tol_opt, jac) if cand.n_groups else \
            (torch.zeros(0, dtype=dt), torch.zeros(0, dtype=torch.long), None)
        raw = torch.zeros(t, dtype=dt).scatter_reduce(0, ft, dep + tol_opt - cfg.tolerance,
                                                      "amax") if len(ft) else torch.zeros(t, dtype=dt)
        pos = dep > 0
        res = [(dep[pos], ft[pos], None if jd is None else jd[pos], 1.0)]
        if pb.caps is not None:
            ov, fc, jc = _capsule_terms(pb, tr, x, jac)
            res.append((ov, fc, jc, cw))
        e_col = np.zeros(t)
        for r, fr, _, sc in res:
            np.add.at(e_col, fr.numpy(), sc * (r * r).numpy())
        e_col *= live
        um = (pb.w[:, None, None] * u_).numpy().reshape(t, -1)
        xm = x0m + um
        cost = float((lam * e_col).sum() / t + lc * (um ** 2).sum() + ls * (_d2(xm) ** 2).sum())
        return cost, e_col, raw.numpy() * live, res, xm

    def refresh(u_: torch.Tensor) -> _Candidates:
        with torch.no_grad():
            tr = body.joint_transforms(pb.pose(u_), pb.betas)
        return _candidates(model, tr, cfg.refresh_margin + cfg.clearance)

    mu, it, best = 1e-3, 0, (float("inf"), float("inf"), u.clone())
    growth = cfg.solver_lambda_growth
    since_refresh, converged, rel = None, False, 0.0
    while it < cfg.solver_iterations:
        if since_refresh is None or since_refresh >= cfg.solver_refresh_every:
            cand = refresh(u)
            since_refresh = 0
            cost, e_col, raw, res, xm = evaluate(u, True)
            pen = raw > cfg.tolerance
            key = (float(np.clip(raw, 0, None).sum()), cost)
            if key < best[:2]:
                best = (*key, u.clone())
            if not pen.any() and it > 0 and converged:
                break
        it += 1
        # which mask joints matter: any non-zero column of a residual Jacobian
        for _, _, jm, _ in res:
            if jm is not None and len(jm):
                variables |= (jm.abs().sum((0, 2)) > 0).numpy() & allowed
        var = np.flatnonzero(variables)
        if len(var) == 0:
            break
        p = 3 * len(var)
        cols = (var[:, None] * 3 + np.arange(3)).ravel()              # into (3K,)
        n = t * p
        diag_blocks = np.zeros((t, p, p))
        g = np.zeros((t, p))
        for r, fr, jm, sc in res:
            if jm is None or len(r) == 0:
                continue
            jv = jm[:, var].reshape(len(r), p).numpy() * wn[fr.numpy()][:, None]
            wgt = sc * lam[fr.numpy()] / t
            rows = jv * np.sqrt(wgt)[:, None]
            frn = fr.numpy()
            order = np.argsort(frn, kind="stable")
            bounds = np.searchsorted(frn[order], np.arange(t + 1))
            rs = r.numpy()
            for ti in np.flatnonzero(np.diff(bounds)):
                sl = order[bounds[ti]:bounds[ti + 1]]
                diag_blocks[ti] += rows[sl].T @ rows[sl]
                g[ti] += (jv[sl] * (wgt[sl] * rs[sl])[:, None]).sum(0)
        um = xm - x0m
        g += (lc * wn[:, None] * um)[:, cols]
        g += (ls * (d2w.T @ _d2(xm)))[:, cols]
        hd = np.einsum("tpp->tp", diag_blocks) + lc * wn[:, None] ** 2
        ab = np.zeros((2 * p + 1, n))
        # block-diagonal collision terms (offsets < p)
        for off in range(p):
            ab[2 * p - off, off:] = _block_band(diag_blocks, off, p, t)[off:]
        for dtt, off in ((1, p), (2, 2 * p)):
            band = np.zeros(n)
            vals = ls * np.diagonal(smooth_n, dtt)                   # (t − dtt,)
            band[off:] = np.repeat(vals, p)
            ab[2 * p - off] += band
        base = hd.ravel() + ls * np.repeat(np.diagonal(smooth_n), p)
        gv = g.ravel()
        accepted = False
        while mu < 1e8:
            abm = ab.copy()
            abm[2 * p] = base * (1 + mu) + 1e-12
            try:
                step = _banded_solve(abm, -gv, 2 * p)

            except np.linalg.LinAlgError:
                mu *= 10
                continue
            du = torch.zeros(t, k, 3, dtype=dt)
            du[:, var] = torch.as_tensor(step.reshape(t, len(var), 3))
            trial = u + du * torch.as_tensor(live, dtype=dt)[:, None, None]
            c_new, e_new, raw_new, res_new, xm_new = evaluate(trial, True)
            if c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-30)
                u, cost, e_col, raw, res, xm = trial, c_new, e_new, raw_new, res_new, xm_new
                mu = max(mu / 3, 1e-7)
                accepted = True
                break
            mu *= 4
        since_refresh += 1
        if _DEBUG:
            print(f"it {it} acc {accepted} mu {mu:.1e} cost {cost:.4g} raw_max {raw.max()*1e3:.2f}mm "
                  f"pen {(raw > cfg.tolerance).sum()} var {len(var)} groups {cand.n_groups}", flush=True)
        converged = (not accepted) or rel < cfg.solver_rtol
        pen = raw > cfg.tolerance
        if pen.any():  # λ continuation: the collision term acts as a constraint
            lam = np.where(pen, np.minimum(lam * growth, cfg.lambda_max), lam)
            cost, e_col, raw, res, xm = evaluate(u, True)
        elif converged:
            since_refresh = cfg.solver_refresh_every  # verify with a fresh broad phase
    cand = refresh(u)
    cost, _, raw, _, _ = evaluate(u, False)
    key = (float(np.clip(raw, 0, None).sum()), cost)
    if key < best[:2]:
        best = (*key, u.clone())
    out = motion.pose.copy()
    delta = torch.zeros_like(pb.x0)
    delta[:, mask_pose] = pb.w[:, None, None] * best[2]
    # x0 + 0.0 is x0: unmasked joints and zero-weight frames stay the input, bit for bit
    out[lo:hi] += delta.numpy().astype(out.dtype)
    return out, it


def _banded_solve(ab: np.ndarray, rhs: np.ndarray, bw: int) -> np.ndarray:
    """Solve the SPD system in upper banded storage `ab` (bw+1, n) as block-tridiagonal
    (blocks of `bw`) by block Cholesky: predictable single-threaded cost ~ n·bw²."""
    n = ab.shape[1]
    m = -(-n // bw)
    size = m * bw
    dense_diag = np.zeros((m, bw, bw))
    off = np.zeros((m, bw, bw))  # off[i] = A[block i, block i+1]
    # scatter bands into blocks
    for o in range(bw + 1):
        j = np.arange(o, n)
        i = j - o
        v = ab[bw - o, o:]
        bi, bj = i // bw, j // bw
        same = bi == bj
        dense_diag[bi[same], i[same] % bw, j[same] % bw] = v[same]
        dense_diag[bi[same], j[same] % bw, i[same] % bw] = v[same]
        nxt = ~same
        off[bi[nxt], i[nxt] % bw, j[nxt] % bw] = v[nxt]
    if size > n:  # pad with identity
        pad = np.arange(n, size)
        dense_diag[pad // bw, pad % bw, pad % bw] = 1.0
    b = np.zeros(size)
    b[:n] = rhs
    b = b.reshape(m, bw)
    chol = np.zeros_like(dense_diag)
    low = np.zeros_like(off)  # low[i] = L[i+1, i]
    y = np.zeros_like(b)
    for i in range(m):
        a = dense_diag[i] - (low[i - 1] @ low[i - 1].T if i else 0.0)
        chol[i] = np.linalg.cholesky(a)
        rhs_i = b[i] - (low[i - 1] @ y[i - 1] if i else 0.0)
        y[i] = solve_triangular(chol[i], rhs_i, lower=True, check_finite=False)
        if i + 1 < m:
            low[i] = solve_triangular(chol[i], off[i], lower=True, check_finite=False).T
    x = np.zeros_like(b)
    for i in range(m - 1, -1, -1):
        rhs_i = y[i] - (low[i].T @ x[i + 1] if i + 1 < m else 0.0)
        x[i] = solve_triangular(chol[i].T, rhs_i, lower=False, check_finite=False)
    return x.ravel()[:n]


def _d2(x: np.ndarray) -> np.ndarray:
    """Second differences (t, m) → padded so that d2wᵀ @ _d2 lines up: (t − 2, m)."""
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def _block_band(blocks: np.ndarray, off: int, p: int, t: int) -> np.ndarray:
    """The `off`-th super-diagonal (length t·p, aligned to the column) of block-diag(blocks)."""
    out = np.zeros(t * p)
    i = np.arange(p - off)
    vals = blocks[:, i, i + off]                                    # (t, p − off)
    cols = (np.arange(t)[:, None] * p + i[None, :] + off).ravel()
    out[cols] = vals.ravel()
    return out
