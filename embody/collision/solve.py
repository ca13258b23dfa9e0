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
- *Cheap evaluations*: the broad phase (`contacts`, margin `solver_refresh_margin`) runs
  every `solver_refresh_every` LM steps; in between its point rows are re-evaluated (skinned,
  planes of their piece by one small matmul per piece, deepest piece per (point, part)) and
  the Jacobian is built only for the rows deeper than the target, over the arm chain (the
  finger joints stay out). Kinematics, depths and Jacobians are float32, the normal
  equations float64; BLAS runs on `threads` (OpenBLAS's spinning threads made the small
  products ~100x slower on a loaded machine).
- *External faces* (`external_faces`): inside a piece the depth is measured to the piece's
  faces that are on the outside of the body, not to faces where two torso pieces abut. The
  nearest-face push of a forearm deep in the chest at the spine1/spine3 seam pointed through
  the seam from both sides and cancelled (the saddle that stalled seq_000/seq_003 at 14/58 mm).
- λ continuation: a frame's λ (from `solver_lambda_col`) grows by `solver_lambda_growth`
  while it still penetrates beyond `tolerance`, but only once the LM step at the current λ
  has settled (`solver_rtol`): growing it every iteration overshot (Pose MSE 2-6x, ΔAccel
  10-100x Adam's on seqs 0, 1, 3). The solve does not stop while a frame penetrates (the
  iteration budget bounds it).

Status (opt-in, `collision.solver: gauss_newton`; 2026-11-26, one thread, CPU seconds by
`time.process_time`, `depth_metrics` off so the optimiser alone): on default seqs 0-3 1.39 CPU s
per 150 frames against Adam's 7.08 (100 vs 909 iterations), Pose MSE 0.0204/0.0096/0.0002/0.0355
(Adam 0.0229/0.0093/0.0002/0.0280). Not yet the default: seq_000's hands interlocked by the
fingers (the finger joints are not variables) oscillate until the 40-iteration cap, seq_003's
correction has kinks (ΔAccel +1.6e-2) and the ≤ 1 s per 150 frames target needs ~2x fewer
iterations. `optimize._mitigate` hands the frames this solve leaves penetrating to Adam,
warm-started from its pose (11 of the 24 default sequences; the figures are in the git log of
2026-11-26).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from scipy.linalg import solveh_banded
from threadpoolctl import threadpool_limits

from embody.body.base import BodyModel
from embody.collision.capsules import Capsules, segment_closest
from embody.collision.energy import (_PAD_PLANE, CollisionModel, PointRows, _affine, _blend,
                                     _box_distance, _piece_planes, contacts, deepest_per_point,
                                     rows_in_part)
from embody.collision.volumes import part_volumes
from embody.config.collision import CollisionConfig
from embody.motion import JOINT_NAMES, Motion, smoothness_scale

#: Print one line per LM iteration (set EMBODY_SOLVE_DEBUG=1).
_DEBUG = bool(os.environ.get("EMBODY_SOLVE_DEBUG"))
#: Precision of the kinematics, depths and Jacobians (the normal equations are float64): float32
#: converges in the same iterations to the same metrics, for about a quarter less CPU.
_DTYPE = torch.float32
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


def external_faces(body: BodyModel, model: CollisionModel, betas: np.ndarray,
                   max_overfill: float) -> np.ndarray:
    """(P,F) bool: the faces of each piece that are on the outside of the body.

    Why: a part's SDF is the min over its own pieces, and the torso is several parts (spine1,
    spine3, ...) whose pieces abut. A forearm point deep in the chest near the seam of two
    pieces is pushed through the nearest face of each, which are the two abutting (internal)
    faces: opposite pushes that cancel (the saddle that stalled seq_000/seq_003). A face is
    internal when its centroid, 3 mm out along its normal (rest pose), lies inside another
    piece of the same part or of a part it is not checked against (an adjacent part). The
    solver measures a point that is inside a piece by its external faces only: the region
    (energy 0 ⇔ no point inside) is the same, only the depth and push direction change.
    Cached on the model."""
    cache = model.__dict__.setdefault("_external", {})
    if "faces" in cache:
        return cache["faces"]
    vols = part_volumes(body, np.asarray(betas, dtype=np.float64), max_overfill=max_overfill)
    frames = np.linalg.inv(model.rest_inverse)
    part_of = np.array([pc.part for pc in vols.pieces])
    joint_of = np.asarray(vols.part_joints)[part_of]
    out = np.zeros(model.planes.shape[:2], dtype=bool)
    for k, pc in enumerate(vols.pieces):
        rot, tr = frames[joint_of[k], :3, :3], frames[joint_of[k], :3, 3]
        pl = np.asarray(pc.planes)
        dist = np.abs(pc.vertices @ pl[:, :3].T + pl[:, 3])                  # (V,F)
        on = dist <= np.maximum(dist.min(0, keepdims=True), 1e-6) + 1e-6
        cen = (on.T @ pc.vertices) / on.sum(0)[:, None]                       # (F,3) joint frame
        probe = (cen + 0.003 * pl[:, :3]) @ rot.T + tr                         # world
        inside = np.zeros(len(pl), dtype=bool)
        for k2, pc2 in enumerate(vols.pieces):
            b, b2 = part_of[k], part_of[k2]
            if k2 == k or (b != b2 and model.checked[b, b2]):
                continue
            r2, t2 = frames[joint_of[k2], :3, :3], frames[joint_of[k2], :3, 3]
            q = (probe - t2) @ r2
            pl2 = np.asarray(pc2.planes)
            inside |= (q @ pl2[:, :3].T + pl2[:, 3]).max(1) < 0
        ext = ~inside
        if not ext.any():
            ext[:] = True
        out[k, :len(pl)] = ext
    cache["faces"] = out
    return out


def _external_planes(model: CollisionModel, ext: np.ndarray, dtype: torch.dtype
                     ) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Each piece's external planes (a list, for `_piece_planes`) and the same packed into a
    padded (P,F,4) tensor, so a plane index of the list addresses it."""
    cache = model.__dict__.setdefault("_external", {})
    key = (dtype, ext.tobytes())
    if key not in cache:
        planes = model.planes
        packed = np.tile(np.array(_PAD_PLANE), (planes.shape[0], planes.shape[1], 1))
        own = []
        for k in range(planes.shape[0]):
            rows = planes[k, ext[k]]
            packed[k, :len(rows)] = rows
            own.append(torch.as_tensor(np.ascontiguousarray(rows), dtype=dtype))
        cache[key] = (own, torch.as_tensor(packed, dtype=dtype))
    return cache[key]


@dataclass
class _Selection:
    """(point, part) groups deeper than the tolerance: frame, chunk, point, part b, the
    winning plane (G,4) in part b's joint frame and the depth (G,) behind it."""

    t: torch.Tensor
    h: torch.Tensor
    n: torch.Tensor
    b: torch.Tensor
    plane: torch.Tensor
    depth: torch.Tensor


def _select(model: CollisionModel, ext: tuple[list[torch.Tensor], torch.Tensor],
            rows: PointRows, transforms: torch.Tensor, tol: float) -> _Selection:
    """The deepest piece per (point, part) among the candidate `rows` whose depth exceeds
    `tol` (negative: within −tol outside). Inside a piece the depth is taken to its external
    faces (`external_faces`), outside it to its nearest face."""
    d = model.tensors(transforms.dtype, transforms.device)
    q = rows_in_part(d, transforms, rows)
    r = torch.nonzero(_box_distance(q, d["piece_box"][rows.k]) <= max(0.0, -tol)).squeeze(1)
    f, arg = _piece_planes(model, d, rows.k[r], q[r])
    keep = f < -tol
    r, f, arg, q = r[keep], f[keep], arg[keep], q[r[keep]]
    k = rows.k[r]
    own, packed = ext
    fe, arge = _piece_planes(model, d, k, q, own)
    inside = f <= 0
    fsel = torch.where(inside, fe, f)
    plane = torch.where(inside[:, None], packed[k, arge], d["planes"][k, arg])
    w = deepest_per_point(d, rows.t[r], rows.h[r], rows.n[r], rows.b[r], fsel)
    rw = r[w]
    return _Selection(rows.t[rw], rows.h[rw], rows.n[rw], rows.b[rw], plane[w], -fsel[w])


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


def _point_jacobian(pb: _Problem, sel: _Selection, transforms: torch.Tensor,
                    joints: np.ndarray | None = None) -> torch.Tensor:
    """(G,K,3) d depth / d x over the mask joints (or the `joints` subset of them, indices
    into the mask) of the selected (point, part) groups."""
    js = np.arange(len(pb.mask_body)) if joints is None else np.asarray(joints)
    mask_body = pb.mask_body[js]
    d = pb.model.tensors(transforms.dtype, transforms.device)
    blend = _blend(d, transforms)
    cj = d["chunk_joints"][sel.h]                                   # (G,U)
    wts = d["chunk_weights"][sel.h, sel.n]                          # (G,U)
    v = d["chunk_points"][sel.h, sel.n]                             # (G,3)
    pu = _affine(blend[sel.t[:, None], cj], v[:, None, :])          # (G,U,3)
    p = (wts[..., None] * pu).sum(1)                                # (G,3)
    jb = d["part_joints"][sel.b]
    nrm = (transforms[sel.t, jb, :3, :3] @ sel.plane[:, :3, None]).squeeze(-1)  # (G,3) world
    tf = transforms[sel.t][:, mask_body]                            # (G,K,4,4)
    o = tf[..., :3, 3]
    desc = pb.desc[mask_body].to(transforms.dtype)                  # (K,J)
    below = wts[:, None, :] * desc[:, cj].permute(1, 0, 2)          # (G,K,U) w_u [u ⊑ k]
    lever = below @ pu                                              # (G,K,3)
    ca = below.sum(-1, keepdim=True)
    cb = desc[:, jb].T[..., None]                                   # (G,K,1)
    vec = torch.linalg.cross(cb * (p[:, None] - o) - (lever - ca * o),
                             nrm[:, None].expand_as(o))
    dd = (vec[..., None, :] @ tf[..., :3, :3]).squeeze(-2)          # (G,K,3) d depth / dδ
    return (dd[..., None, :] @ pb.jr[sel.t][:, js].to(transforms.dtype)).squeeze(-2)


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
    """LM over the masked joints of the frames with weight > 0; returns (pose, iterations).
    BLAS runs on `cfg.threads` threads: its small banded and block products ran ~100x slower
    with OpenBLAS's threads spinning on a loaded machine."""
    with threadpool_limits(limits=cfg.threads, user_api="blas"):
        return _solve(body, model, motion, idx, weight, cfg, caps)


def _solve(body: BodyModel, model: CollisionModel, motion: Motion, idx: np.ndarray,
           weight: np.ndarray, cfg: CollisionConfig,
           caps: Capsules | None) -> tuple[np.ndarray, int]:
    active = np.flatnonzero(weight > 0)
    lo, hi = int(active[0]), int(active[-1]) + 1
    names = list(body.joint_names)
    keep = [j for j in idx if JOINT_NAMES[j] in names]
    mask_pose = np.array(keep, dtype=np.int64)
    mask_body = np.array([names.index(JOINT_NAMES[j]) for j in keep], dtype=np.int64)
    dt = _DTYPE
    pb = _Problem(body, model, caps if caps is not None and len(caps.reach) else None, cfg,
                  torch.as_tensor(motion.pose[lo:hi], dtype=dt),
                  torch.as_tensor(weight[lo:hi], dtype=dt),
                  torch.as_tensor(motion.betas, dtype=dt), mask_pose, mask_body,
                  torch.as_tensor(_descendants(np.asarray(body.parents)), dtype=dt))
    ext = _external_planes(model, external_faces(body, model, motion.betas, cfg.max_overfill), dt)
    t, k = pb.x0.shape[0], len(mask_pose)
    wn = weight[lo:hi]
    live = wn > 0
    tol_opt = cfg.tolerance - cfg.clearance
    lam = np.full(t, float(cfg.solver_lambda_col))
    # `lambda_smooth` is stated at 30 fps: the same correction costs the same at any rate
    lc, ls, cw = cfg.lambda_close / t, cfg.lambda_smooth * smoothness_scale(motion.fps, 2) / t, cfg.capsule_weight
    d2w, smooth_n = _smooth_ops(wn)
    x0m = pb.x0[:, mask_pose].double().numpy().reshape(t, -1)        # (t, 3K)
    # finger joints stay out of the solve when the mask also holds the arm chain: the arm
    # separates the parts and the banded system stays narrow (3 x 8 unknowns per frame; with
    # all 38 arm-mask joints one solve took seconds). Only joints that move a residual count.
    fingers = mask_pose >= FIRST_FINGER
    aidx = np.flatnonzero(~fingers if (~fingers).any() else fingers)  # into the mask
    variables = np.zeros(len(aidx), dtype=bool)
    rows: PointRows | None = None

    def evaluate(u_: torch.Tensor) -> dict:
        """Residuals with their Jacobians, per-frame collision energy and worst depth."""
        x = pb.pose(u_)
        tr = body.joint_transforms(x, pb.betas)
        pb.jr = right_jacobian(x[:, pb.mask_pose])
        res = []
        raw = np.zeros(t)
        if rows is not None and rows.t.numel():
            sel = _select(model, ext, rows, tr, tol_opt)
            if len(sel.t):
                res.append((sel.depth - tol_opt, sel.t, _point_jacobian(pb, sel, tr, aidx),
                            1.0))
                np.maximum.at(raw, sel.t.numpy(), (sel.depth - cfg.tolerance).double().numpy())
        if pb.caps is not None:
            ov, fc, jc = _capsule_terms(pb, tr, x, True)
            if len(ov):
                res.append((ov, fc, jc[:, aidx], cw))
        e_col = np.zeros(t)
        for r, fr, _, sc in res:
            np.add.at(e_col, fr.numpy(), sc * (r.double() ** 2).numpy())
        e_col *= live
        um = (pb.w[:, None, None] * u_).double().numpy().reshape(t, -1)
        xm = x0m + um
        prior = float(lc * (um ** 2).sum() + ls * (_d2(xm) ** 2).sum())
        return dict(u=u_, res=res, e_col=e_col, raw=raw * live, xm=xm, prior=prior)

    def cost(ev: dict) -> float:
        return float((lam * ev["e_col"]).sum() / t) + ev["prior"]

    def refresh(u_: torch.Tensor) -> PointRows:
        with torch.no_grad():
            tr = body.joint_transforms(pb.pose(u_), pb.betas)
        return contacts(model, tr, cfg.solver_refresh_margin + cfg.clearance).points

    u = torch.zeros(t, k, 3, dtype=dt)
    rows = refresh(u)
    ev = evaluate(u)
    mu, it, since_refresh = 1e-3, 0, 0
    best = (float("inf"), float("inf"), u.clone())
    growth = cfg.solver_lambda_growth

    def record(ev: dict) -> None:  # only right after a refresh: the candidates are complete
        nonlocal best
        key = (float(np.clip(ev["raw"], 0, None).sum()), cost(ev))
        if key < best[:2]:
            best = (*key, ev["u"].clone())

    record(ev)
    while it < cfg.solver_iterations:
        it += 1
        res = ev["res"]
        for _, _, jm, _ in res:
            if len(jm):
                variables |= (jm.abs().sum((0, 2)) > 0).numpy()
        var = np.flatnonzero(variables)
        if len(var) == 0:
            break
        p = 3 * len(var)
        cols = (aidx[var][:, None] * 3 + np.arange(3)).ravel()        # into (3K,)
        n = t * p
        diag_blocks = np.zeros((t, p, p))
        g = np.zeros((t, p))
        for r, fr, jm, sc in res:
            if len(r) == 0:
                continue
            frn = fr.numpy()
            jv = jm[:, var].reshape(len(r), p).double().numpy() * wn[frn][:, None]
            wgt = sc * lam[frn] / t
            jw = jv * wgt[:, None]
            order = np.argsort(frn, kind="stable")
            bounds = np.searchsorted(frn[order], np.arange(t + 1))
            rs = r.double().numpy()
            for ti in np.flatnonzero(np.diff(bounds)):
                sl = order[bounds[ti]:bounds[ti + 1]]
                diag_blocks[ti] += jw[sl].T @ jv[sl]
                g[ti] += rs[sl] @ jw[sl]
        xm = ev["xm"]
        um = xm - x0m
        g += (lc * wn[:, None] * um)[:, cols]
        g += (ls * (d2w.T @ _d2(xm)))[:, cols]
        hd = np.einsum("tpp->tp", diag_blocks) + lc * wn[:, None] ** 2
        ab = np.zeros((2 * p + 1, n))
        for off in range(p):  # block-diagonal collision terms (offsets < p)
            ab[2 * p - off, off:] = _block_band(diag_blocks, off, p, t)[off:]
        for dtt, off in ((1, p), (2, 2 * p)):
            band = np.zeros(n)
            band[off:] = np.repeat(ls * np.diagonal(smooth_n, dtt), p)
            ab[2 * p - off] += band
        base = hd.ravel() + ls * np.repeat(np.diagonal(smooth_n), p)
        gv = g.ravel()
        c0 = cost(ev)
        accepted, rel = False, 0.0
        for _ in range(cfg.solver_trials):
            abm = ab.copy()
            abm[2 * p] = base * (1 + mu) + 1e-12
            try:
                step = _banded_solve(abm, -gv, 2 * p)
            except np.linalg.LinAlgError:
                mu *= 10
                continue
            du = torch.zeros(t, k, 3, dtype=dt)
            du[:, aidx[var]] = torch.as_tensor(step.reshape(t, len(var), 3), dtype=dt)
            trial = evaluate(ev["u"] + du * torch.as_tensor(live, dtype=dt)[:, None, None])
            c1 = cost(trial)
            if c1 < c0:
                rel = (c0 - c1) / max(c0, 1e-30)
                ev, mu, accepted = trial, max(mu / 3, 1e-7), True
                break
            mu *= 4
        since_refresh += 1
        pen = ev["raw"] > 0
        if _DEBUG:
            print(f"it {it} acc {accepted} mu {mu:.1e} cost {cost(ev):.4g} "
                  f"raw_max {ev['raw'].max()*1e3:.2f}mm pen {pen.sum()} var {len(var)} "
                  f"rows {rows.t.numel()}", flush=True)
        converged = (not accepted) or rel < cfg.solver_rtol
        if pen.any() and converged:
            # λ continuation once the step at this λ has settled (growing it at every
            # iteration overshot: Pose MSE 2-6x and ΔAccel 10-100x Adam's on seqs 0, 1, 3)
            lam = np.where(pen, np.minimum(lam * growth, cfg.lambda_max), lam)
            converged = False
        if (since_refresh >= cfg.solver_refresh_every or (converged and not pen.any())
                or it == cfg.solver_iterations):
            rows = refresh(ev["u"])
            ev = evaluate(ev["u"])
            since_refresh = 0
            record(ev)
            if converged and not (ev["raw"] > 0).any():
                break
    out = motion.pose.copy()
    delta = torch.zeros_like(pb.x0)
    delta[:, mask_pose] = pb.w[:, None, None] * best[2]
    # x0 + 0.0 is x0: unmasked joints and zero-weight frames stay the input, bit for bit
    out[lo:hi] += delta.numpy().astype(out.dtype)
    return out, it


def _banded_solve(ab: np.ndarray, rhs: np.ndarray, bw: int) -> np.ndarray:
    """Solve the SPD system in upper banded storage `ab` (bw+1, n): one LAPACK banded
    Cholesky (`pbsv`, cost ~ n·bw²). Raises LinAlgError when it is not positive definite."""
    return solveh_banded(ab, rhs, lower=False, check_finite=False)


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
