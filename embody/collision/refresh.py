"""The optimiser's broad-phase refresh, frame by frame: a frame's candidate rows are kept while
its points cannot have moved far, relative to any part, since the pose they were found at.

Why: the refresh (`energy.contacts` every `refresh_every` steps, ~14-20 ms) was ~30 % of Adam's
optimiser, yet between two refreshes most frames move a few millimetres against a margin of
centimetres. The rows are only candidates: the narrow phase keeps the points within `reach` of a
piece. A frame's rows found at pose P₀ with margin m hold every such point of any pose whose
points moved less than m − reach from P₀ in every part's frame (every level of the broad phase
is a conservative, 1-Lipschitz test with margin m), exactly as the rows of a fresh refresh hold
those of the steps until the next one. So a frame is refreshed only when the bound
`displacement` on that motion passes `budget` (half of m − reach: the other half is left for
the steps until the next refresh, as much as a fresh refresh leaves them in practice) and the
narrow phase selects the same points, planes and values from either set of rows: the same
energies and poses (`tests/test_collision_refresh.py` checks them against fresh refreshes).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from numba import njit

from embody.collision.energy import CollisionModel, Contacts, broad_rows, contacts, contacts_of


def joint_levers(model: CollisionModel) -> np.ndarray:
    """(J,) the farthest any model point skinned by joint j lies from j's origin, in j's frame
    (0 for joints that skin none): with B_j = A_j·Rinv_j a point moves by at most
    ‖ΔR_j‖·lever_j + |Δt_j| when A_j = [R_j | t_j] changes."""
    cache = model.__dict__.setdefault("_refresh", {})
    if "levers" not in cache:
        rinv = model.rest_inverse
        out = np.zeros(len(rinv))
        used = (model.chunk_weights > 0) & model.chunk_mask[..., None]            # (H,S,U)
        for h, s, u in zip(*np.nonzero(used)):
            j = model.chunk_joints[h, u]
            local = rinv[j, :3, :3] @ model.chunk_points[h, s] + rinv[j, :3, 3]
            out[j] = max(out[j], float(np.linalg.norm(local)))
        cache["levers"] = out
    return cache["levers"]


def part_reaches(model: CollisionModel, margin: float) -> np.ndarray:
    """(C,) how far from part b's joint origin a point within 2·`margin` (the broad phase's
    point margin) of one of b's piece boxes can lie: the farthest box corner plus that."""
    cache = model.__dict__.setdefault("_refresh", {})
    if ("reach", margin) in cache:
        return cache[("reach", margin)]
    corners = np.abs(model.piece_box).max(1)                                     # (P,3)
    far = np.linalg.norm(corners, axis=1)
    out = np.zeros(len(model.part_joints))
    for b, ks in enumerate(model.part_pieces):
        ks = ks[ks >= 0]
        out[b] = far[ks].max() + 2.0 * margin
    cache[("reach", margin)] = out
    return out


def displacement(model: CollisionModel, margin: float, old: torch.Tensor,
                 new: torch.Tensor) -> torch.Tensor:
    """(T,) an upper bound on how far any model point moves relative to any part's joint frame
    between joint transforms `old` and `new` (T,J,4,4), for points near that part.

    A point p = Σ_u w_u B_u v (weights ≥ 0 summing to 1) moves by at most
    max_u ‖ΔR_u‖·lever_u + |Δt_u|; in part b's frame, q = R_bᵀ(p − t_b) moves by at most
    that plus |Δt_b| + ‖ΔR_b‖·|q|. For rotations ‖R₁ − R₀‖₂ = ‖R₁ − R₀‖_F/√2 (both singular
    values of the difference are 2 sin(θ/2)); 1e-6 m is added for rounding."""
    return torch.from_numpy(_displacement(
        old.detach().contiguous().numpy(), new.detach().contiguous().numpy(),
        joint_levers(model), model.part_joints, part_reaches(model, margin)))


@njit(cache=True, nogil=True)
def _displacement(old: np.ndarray, new: np.ndarray, lever: np.ndarray, part_joints: np.ndarray,
                  reach: np.ndarray) -> np.ndarray:
    """Per frame, a bound on how far any model point moved between the transforms `old` and
    `new` (every joint may differ)."""
    return _displacement_at(old, new, np.arange(old.shape[1]), lever, part_joints, reach)


@njit(cache=True, nogil=True)
def _displacement_at(old: np.ndarray, new: np.ndarray, joints: np.ndarray, lever: np.ndarray,
                     part_joints: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """`_displacement` when only `joints` can differ between `old` and `new`: the same
    values (the other joints' ΔR and Δt are 0, adding 0 to either maximum of non-negative
    terms), over those joints only and with no gather of the live frames first."""
    n_t, n_j = old.shape[0], old.shape[1]
    out = np.empty(n_t)
    rot = np.zeros(n_j)
    shift = np.zeros(n_j)
    for t in range(n_t):
        point = 0.0
        for j in joints:
            r = 0.0
            for a in range(3):
                for c in range(3):
                    d = np.float64(new[t, j, a, c]) - np.float64(old[t, j, a, c])
                    r += d * d
            s = 0.0
            for a in range(3):
                d = np.float64(new[t, j, a, 3]) - np.float64(old[t, j, a, 3])
                s += d * d
            rot[j], shift[j] = np.sqrt(0.5 * r), np.sqrt(s)
            point = max(point, rot[j] * lever[j] + shift[j])
        part = 0.0
        for b in range(len(part_joints)):
            j = part_joints[b]
            part = max(part, rot[j] * reach[b] + shift[j])
        out[t] = point + part + 1e-6
    return out


class Refresh:
    """Candidate rows (`energy.Contacts`) of the live frames, each frame's refreshed only when
    its `displacement` since its rows were found passes `budget`."""

    def __init__(self, model: CollisionModel, margin: float, reach: float,
                 frames: torch.Tensor | None, joints: np.ndarray | None = None) -> None:
        self.model, self.margin = model, margin
        # the only joints whose transforms can change between calls (None: any): the bound
        # runs over them alone (the others' ΔR and Δt are 0 and add nothing to its maxima)
        self.joints = None if joints is None else np.asarray(joints, dtype=np.int64)
        self.budget = 0.5 * (margin - reach)
        self.frames = frames  # the live frames (all when None)
        self.ref: torch.Tensor | None = None  # per frame, the transforms its rows were found at
        self.arrays: tuple[np.ndarray, np.ndarray] | None = None  # `broad_rows`' (rows, pts)
        self.rows: Contacts | None = None
        self.refreshed = 0  # frames refreshed, over all calls (for benchmarks)

    def __call__(self, transforms: torch.Tensor) -> Contacts:
        """The rows for `transforms` (the optimiser's refresh steps): the frames that moved
        more than `budget` since their rows were found get fresh ones."""
        tr = transforms.detach()
        live = torch.arange(tr.shape[0], device=tr.device) if self.frames is None \
            else self.frames
        if tr.device.type != "cpu":  # other devices: every live frame at each refresh step
            c = contacts(self.model, tr.index_select(0, live), self.margin)
            self.rows = replace(c, t=live[c.t], points=replace(c.points, t=live[c.points.t]))
            return self.rows
        if self.ref is None or self.arrays is None or self.rows is None:
            stale = live
        else:
            if self.joints is None:
                moved = displacement(self.model, self.margin, self.ref[live], tr[live])
            else:
                moved = torch.from_numpy(_displacement_at(
                    self.ref.numpy(), tr.contiguous().numpy(), self.joints,
                    joint_levers(self.model), self.model.part_joints,
                    part_reaches(self.model, self.margin)))[live]
            stale = live[moved > self.budget]
            if len(stale) == 0:
                return self.rows
        rows, pts = broad_rows(self.model, tr.index_select(0, stale), self.margin)
        frames = stale.numpy()
        rows[:, 0], pts[:, 0] = frames[rows[:, 0]], frames[pts[:, 0]]
        self.refreshed += len(stale)
        if self.ref is None or self.arrays is None:
            self.ref = tr.clone()
        else:
            self.ref[stale] = tr[stale]
            redo = np.zeros(tr.shape[0], dtype=np.bool_)
            redo[frames] = True
            rows = _merge(self.arrays[0], rows, redo)
            pts = _merge(self.arrays[1], pts, redo)
        self.arrays = rows, pts
        self.rows = contacts_of(self.model, rows, pts)
        return self.rows


@njit(cache=True, nogil=True)
def _merge(old: np.ndarray, fresh: np.ndarray, redo: np.ndarray) -> np.ndarray:
    """The rows of `old` whose frame (column 0) is not in `redo`, and all of `fresh` (whose
    frames are), both in frame order: one merge in frame order, each keeping its own order
    within a frame."""
    out = np.empty((len(old) + len(fresh), old.shape[1]), dtype=old.dtype)
    i = j = n = 0
    while i < len(old) or j < len(fresh):
        if i < len(old) and redo[old[i, 0]]:
            i += 1
        elif j == len(fresh) or (i < len(old) and old[i, 0] < fresh[j, 0]):
            out[n] = old[i]
            n += 1
            i += 1
        else:
            out[n] = fresh[j]
            n += 1
            j += 1
    return out[:n]
