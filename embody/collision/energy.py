"""Volumetric self-collision energy (Eq. 1): L_col = (1/T) Σ_t Σ_v max(0, −f(v; x_t))².

Points are rest-mesh vertices plus the corners of the part's pieces (every `vertex_stride`-th
of each), carried rigidly by their part's joint, i.e. the skinned mesh with one-hot weights:
it costs one transform per part, and with the points kept inside their own part's pieces a
positive energy always means that two checked parts' volumes overlap. f is the signed
distance to a part: the minimum over its convex
pieces of max_f(n_f·q + d_f), exact inside. A broad phase (part spheres, piece boxes, point
boxes) picks (frame, point chunk, piece) rows without gradients; the narrow phase evaluates the
planes of points inside a box and differentiates only the penetrating ones, so the cost follows
the pairs that are actually close.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.collision.exclusions import checked_pairs, part_groups
from embody.collision.volumes import part_volumes, rest_frames, to_local

#: Planes that never win the max: padding for pieces with fewer faces.
_PAD_PLANE = (0.0, 0.0, 0.0, -1e9)


def _sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    center = 0.5 * (points.min(0) + points.max(0))
    return center, float(np.sqrt(((points - center) ** 2).sum(1).max()))


def _inside_own(points: np.ndarray, pieces: list) -> np.ndarray:
    """Guard: `volumes.cover` puts every vertex inside its own part's pieces; any point that
    rounding leaves outside is dropped, so a point inside another part always means that the
    two parts' volumes overlap."""
    f = np.min([np.max(points @ pc.planes[:, :3].T + pc.planes[:, 3], axis=1) for pc in pieces],
               axis=0)
    return f <= 1e-9


def _chunks(points: np.ndarray, size: int) -> list[np.ndarray]:
    """Split point indices by recursive median cuts along the longest axis (deterministic)."""
    def split(idx: np.ndarray) -> list[np.ndarray]:
        if len(idx) <= size:
            return [idx]
        p = points[idx]
        axis = int(np.argmax(p.max(0) - p.min(0)))
        order = idx[np.argsort(p[:, axis], kind="stable")]
        half = len(order) // 2
        return split(order[:half]) + split(order[half:])
    return split(np.arange(len(points)))


@dataclass(frozen=True)
class CollisionModel:
    """Points (in spatial chunks), pieces and checked pairs of one body shape.

    Kept in numpy; `tensors` converts once per dtype/device.
    """

    groups: tuple[str, ...]
    part_names: tuple[str, ...]
    part_joints: np.ndarray      # (C,)
    part_group: np.ndarray       # (C,)
    checked: np.ndarray          # (C,C): points of part a vs pieces of part b
    chunk_part: np.ndarray       # (H,)
    chunk_points: np.ndarray     # (H,S,3) joint-local, padded
    chunk_mask: np.ndarray       # (H,S)
    chunk_center: np.ndarray     # (H,3)
    chunk_radius: np.ndarray     # (H,)
    part_center: np.ndarray      # (C,3) joint-frame sphere around the part's pieces
    part_radius: np.ndarray      # (C,)
    part_pieces: np.ndarray      # (C,K) piece ids, -1 padded
    planes: np.ndarray           # (P,F,4) in the piece's joint frame, padded
    piece_box: np.ndarray        # (P,2,3) joint-frame box of each piece

    @property
    def num_points(self) -> int:
        return int(self.chunk_mask.sum())

    def tensors(self, dtype: torch.dtype, device: torch.device) -> dict[str, torch.Tensor]:
        cache = self.__dict__.setdefault("_tensors", {})
        key = (dtype, device)
        if key not in cache:
            out = {}
            for name in ("part_joints", "checked", "chunk_part", "chunk_points", "chunk_mask",
                         "chunk_center", "chunk_radius", "part_center", "part_radius",
                         "part_pieces", "planes", "piece_box"):
                a = getattr(self, name)
                out[name] = torch.as_tensor(a, device=device,
                                            dtype=dtype if a.dtype == np.float64 else None)
            cache[key] = out
        return cache[key]


_models: weakref.WeakKeyDictionary[BodyModel, dict[tuple, CollisionModel]] = \
    weakref.WeakKeyDictionary()
#: Points per broad-phase chunk.
CHUNK_SIZE = 24


def collision_model(body: BodyModel, betas: np.ndarray | None = None, *, vertex_stride: int = 8,
                    allow_pairs: Iterable[Sequence[str]] = (),
                    max_overfill: float = 0.10) -> CollisionModel:
    """Build (once per body, shape and settings) what the energy evaluates."""
    betas = np.zeros(10) if betas is None else np.asarray(betas, dtype=np.float64)
    vols = part_volumes(body, betas, max_overfill=max_overfill)
    allow = tuple(tuple(p) for p in allow_pairs)
    key = (vols.key, vertex_stride, allow)
    models = _models.setdefault(body, {})
    if key in models:
        return models[key]
    groups, part_group = part_groups(vols.part_names)
    gchecked = checked_pairs(groups, body.joint_names, body.parents, allow)
    rest = body.rest_vertices(torch.as_tensor(betas)).double().numpy()
    frames = rest_frames(body, betas)
    n_parts = len(vols.part_names)
    chunk_part, chunk_pts = [], []
    for i, j in enumerate(vols.part_joints):
        own = [pc for pc in vols.pieces if pc.part == i]
        local = to_local(rest[vols.vertex_parts == i][::vertex_stride], frames[j])
        # the pieces' corners too: they catch overlaps across a piece's flat (vertex-free) faces
        local = np.concatenate([local[_inside_own(local, own)],
                                *[pc.vertices[::vertex_stride] for pc in own]])
        if len(local) == 0:
            continue
        for idx in _chunks(local, CHUNK_SIZE):
            chunk_part.append(i)
            chunk_pts.append(local[idx])
    points = np.zeros((len(chunk_pts), CHUNK_SIZE, 3))
    mask = np.zeros((len(chunk_pts), CHUNK_SIZE), dtype=bool)
    for h, p in enumerate(chunk_pts):
        points[h, :len(p)], mask[h, :len(p)] = p, True
    per_part = [[k for k, pc in enumerate(vols.pieces) if pc.part == i] for i in range(n_parts)]
    part_pieces = np.full((n_parts, max(map(len, per_part))), -1, dtype=np.int64)
    for i, ks in enumerate(per_part):
        part_pieces[i, :len(ks)] = ks
    f_max = max(len(p.planes) for p in vols.pieces)
    planes = np.tile(np.array(_PAD_PLANE), (len(vols.pieces), f_max, 1))
    for k, pc in enumerate(vols.pieces):
        planes[k, :len(pc.planes)] = pc.planes
    chunk_s = [_sphere(p) for p in chunk_pts]
    part_s = [_sphere(np.concatenate([vols.pieces[k].vertices for k in ks])) for ks in per_part]
    box = lambda v: np.stack((v.min(0), v.max(0)))  # noqa: E731
    model = CollisionModel(
        groups=groups, part_names=vols.part_names, part_joints=vols.part_joints,
        part_group=part_group, checked=gchecked[part_group[:, None], part_group[None, :]],
        chunk_part=np.array(chunk_part), chunk_points=points, chunk_mask=mask,
        chunk_center=np.array([c for c, _ in chunk_s]),
        chunk_radius=np.array([r for _, r in chunk_s]),
        part_center=np.array([c for c, _ in part_s]), part_radius=np.array([r for _, r in part_s]),
        part_pieces=part_pieces, planes=planes,
        piece_box=np.array([box(pc.vertices) for pc in vols.pieces]))
    models[key] = model
    return model


def _apply(rot: torch.Tensor, trans: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    return (rot @ p.unsqueeze(-1)).squeeze(-1) + trans


def _box_distance(q: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Euclidean distance from points q (...,3) to boxes (...,2,3) (0 inside)."""
    gap = torch.clamp(box[..., 0, :] - q, min=0) + torch.clamp(q - box[..., 1, :], min=0)
    return gap.norm(dim=-1)


@dataclass(frozen=True)
class Contacts:
    """(frame, chunk, part a, part b, piece) rows whose points may be inside the piece."""

    t: torch.Tensor
    h: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    k: torch.Tensor


def _frames(d: dict[str, torch.Tensor],
            transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    g = transforms[:, d["part_joints"]]                        # (T,C,4,4)
    return g[..., :3, :3], g[..., :3, 3]


def _chunk_local(d: dict[str, torch.Tensor], rot: torch.Tensor, trans: torch.Tensor,
                 c: Contacts) -> torch.Tensor:
    """Points (R,S,3) of chunk h in the joint frame of part b."""
    rel = rot[c.t, c.b].transpose(-1, -2) @ rot[c.t, c.a]      # R_bᵀ R_a
    off = ((trans[c.t, c.a] - trans[c.t, c.b]).unsqueeze(-2) @ rot[c.t, c.b])  # R_bᵀ(t_a − t_b)
    return d["chunk_points"][c.h] @ rel.transpose(-1, -2) + off


def contacts(model: CollisionModel, transforms: torch.Tensor, margin: float = 0.0) -> Contacts:
    """Broad phase (no gradients): chunk-piece rows with a point within `margin` of the piece.

    Level 1 tests chunk spheres against part spheres, level 2 chunk spheres against piece boxes
    in the piece's joint frame, level 3 the chunk's points against those boxes; the exact plane
    test is left to `frame_energies`, point by point.
    """
    d = model.tensors(transforms.dtype, transforms.device)
    with torch.no_grad():
        rot, trans = _frames(d, transforms)
        ca = d["chunk_part"]
        chunk_c = _apply(rot[:, ca], trans[:, ca], d["chunk_center"])           # (T,H,3)
        part_c = _apply(rot, trans, d["part_center"])                            # (T,C,3)
        reach = d["chunk_radius"][:, None] + d["part_radius"] + margin
        near = (torch.cdist(chunk_c, part_c) < reach) & d["checked"][ca]
        ft, fh, fb = torch.nonzero(near, as_tuple=True)
        pieces = d["part_pieces"][fb]                                            # (M,K)
        cq = ((chunk_c[ft, fh] - trans[ft, fb]).unsqueeze(-2) @ rot[ft, fb]).squeeze(-2)
        pk = pieces.clamp(min=0)
        close = _box_distance(cq[:, None, :], d["piece_box"][pk])
        close = (close < d["chunk_radius"][fh, None] + margin) & (pieces >= 0)
        m, ks = torch.nonzero(close, as_tuple=True)
        c = Contacts(ft[m], fh[m], d["chunk_part"][fh[m]], fb[m], pk[m, ks])
        if m.numel():  # level 3: the chunk's points against the piece's box
            q = _chunk_local(d, rot, trans, c)
            pts = (_box_distance(q, d["piece_box"][c.k][:, None]) <= margin) & \
                d["chunk_mask"][c.h]
            hit = pts.any(dim=1)
            c = Contacts(c.t[hit], c.h[hit], c.a[hit], c.b[hit], c.k[hit])
    return c


def frame_energies(model: CollisionModel, transforms: torch.Tensor, tolerance: float = 0.0,
                   near: Contacts | None = None) -> torch.Tensor:
    """Per-frame Σ_v max(0, −f − tolerance)² (T,) from joint world transforms (T,J,4,4).

    `near` reuses a broad phase computed earlier with a margin (the optimiser refreshes it
    every few steps); by default it is computed here, exactly. The deepest piece and plane of
    each penetrating point are picked without gradients; the gradient of a max is that of its
    argmax, so recomputing just that plane with autograd gives the exact gradient at a cost
    that follows the penetrating points only.
    """
    d = model.tensors(transforms.dtype, transforms.device)
    t_frames = transforms.shape[0]
    zero = transforms.new_zeros(t_frames) + 0.0 * transforms[:, :1, 0, 0].sum()
    c = contacts(model, transforms) if near is None else near
    if c.t.numel() == 0:
        return zero
    rot, trans = _frames(d, transforms)
    with torch.no_grad():
        q = _chunk_local(d, rot, trans, c)
        inbox = (_box_distance(q, d["piece_box"][c.k][:, None]) <= 0) & d["chunk_mask"][c.h]
        r, n = torch.nonzero(inbox, as_tuple=True)
        planes = d["planes"][c.k[r]]                                # (Q,F,4)
        f, plane = (torch.bmm(planes[..., :3], q[r, n].unsqueeze(-1)).squeeze(-1)
                    + planes[..., 3]).max(-1)
        inside = f < -tolerance
        r, n, f, plane, planes = r[inside], n[inside], f[inside], plane[inside], planes[inside]
        if r.numel() == 0:
            return zero
        # a part's SDF is the min over its pieces: keep the deepest piece per (frame, point, part)
        n_chunks, n_parts, size = d["chunk_part"].shape[0], d["part_radius"].shape[0], q.shape[1]
        key = ((c.t[r] * n_chunks + c.h[r]) * size + n) * n_parts + c.b[r]
        order = torch.sort(f, stable=True).indices                  # deepest first
        order = order[torch.sort(key[order], stable=True).indices]  # grouped by key
        first = torch.ones_like(order, dtype=torch.bool)
        first[1:] = key[order][1:] != key[order][:-1]
        keep = order[first]
        r, n = r[keep], n[keep]
        t, h, a, b = c.t[r], c.h[r], c.a[r], c.b[r]
        nd = planes[keep, plane[keep]]                              # (Q,4) the active plane
    p = _apply(rot[t, a], trans[t, a], d["chunk_points"][h, n])
    ql = ((p - trans[t, b]).unsqueeze(-2) @ rot[t, b]).squeeze(-2)
    depth = torch.relu(-(ql * nd[:, :3]).sum(-1) - nd[:, 3] - tolerance)
    return zero.index_add(0, t, depth * depth)


def energy(model: CollisionModel, transforms: torch.Tensor, tolerance: float = 0.0) -> torch.Tensor:
    """L_col (Eq. 1): mean over frames of the per-frame energies."""
    return frame_energies(model, transforms, tolerance).mean()


def pose_frame_energies(body: BodyModel, pose: torch.Tensor, betas: torch.Tensor,
                        model: CollisionModel, tolerance: float = 0.0) -> torch.Tensor:
    """Per-frame energies (T,) of a (T,55,3) pose tensor (differentiable in pose)."""
    return frame_energies(model, body.joint_transforms(pose, betas.to(pose)), tolerance)
