"""Volumetric self-collision energy (Eq. 1): L_col = (1/T) Σ_t Σ_v max(0, −f(v; x_t))².

V_t is the linear-blend-skinned mesh, the surface that gets rendered: every `vertex_stride`-th
vertex of each part, skinned only for that subsample (each point chunk gathers the few joints
that weight it). Each point is tested against every checked part it does not belong to (its
dominant-weight part's collision group, see `exclusions`). f is the signed distance to a part:
the minimum over its convex pieces of max_f(n_f·q + d_f), exact inside.

The corners of each part's pieces (same stride) are added as points carried rigidly by their
joint: two convex pieces can overlap across flat, vertex-free faces with no mesh vertex inside
the other. Without the corners one of the validation poses (tests/test_collision_validation.py)
with > 1 cm³ of piece overlap scored 0; with them "energy 0 ⇔ overlap volume 0" holds there.
Near joints, skinned vertices do leave their own part's rigid pieces (≈4% of vertex-frames of
the validation poses, by up to 2 cm): they are the blended vertices around a joint, next to the
parent or child part, which is excluded. No exclusion had to change: the rest pose and clear
poses score exactly 0, and on the validation poses energy is 0 exactly where overlap is 0.

A broad phase (per-frame spheres bounding each chunk's skinned points, part spheres, piece
boxes, point boxes) picks (frame, point chunk, piece) rows without gradients; the narrow phase
evaluates the planes of points inside a box and differentiates only the penetrating ones,
skinning just those points again with autograd, so the cost follows the pairs that are close.
On the CPU the broad phase, the float32 selection and the depths' forward and backward run
compiled (`broad`, `narrow`; the tensor code stays for other devices and as their reference).
SMPL-X pose correctives (posedirs) are left out: the skin is plain LBS of the shaped rest mesh.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.clusters import median_cuts
from embody.collision.broad import broad_phase, index_rows
from embody.collision.exclusions import checked_pairs, part_groups
from embody.collision.narrow import PointDepths, select, select_inputs
from embody.collision.volumes import part_volumes, rest_frames

#: Planes that never win the max: padding for pieces with fewer faces.
_PAD_PLANE = (0.0, 0.0, 0.0, -1e9)
#: Radius slack (m) of the broad phase's chunk spheres: skinning weights stored as float32
#: sum to 1 only within ~1e-7.
_SLACK = 1e-5


def _sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    center = 0.5 * (points.min(0) + points.max(0))
    return center, float(np.sqrt(((points - center) ** 2).sum(1).max()))


def _influences(weights: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(joints (U,), weights (size,U)) of one chunk: the joints with a non-zero weight on any
    of its points. Chunks are small and spatial, so U stays small (≤ 8 on the mannequin) and
    skinning a chunk gathers U transforms, not one set per point."""
    joints = np.flatnonzero((weights > 0).any(0))
    out = np.zeros((size, len(joints)))
    out[:len(weights)] = weights[:, joints]
    return joints, out


@dataclass(frozen=True)
class CollisionModel:
    """Points (in spatial chunks, with their skin), pieces and checked pairs of one body shape.

    Kept in numpy; `tensors` converts once per dtype/device.
    """

    groups: tuple[str, ...]
    part_names: tuple[str, ...]
    part_joints: np.ndarray      # (C,)
    part_group: np.ndarray       # (C,)
    checked: np.ndarray          # (C,C): points of part a vs pieces of part b
    chunk_part: np.ndarray       # (H,)
    chunk_points: np.ndarray     # (H,S,3) rest-pose world positions, padded
    chunk_joints: np.ndarray     # (H,U) joints that skin the chunk (corners: their own joint)
    chunk_weights: np.ndarray    # (H,S,U) skinning weights over those joints, 0 for padding
    chunk_mask: np.ndarray       # (H,S)
    chunk_used: np.ndarray       # (H,U) which of chunk_joints are real (not padding)
    chunk_center: np.ndarray     # (H,3) rest-pose sphere around the chunk's points
    chunk_radius: np.ndarray     # (H,)
    rest_inverse: np.ndarray     # (J,4,4) inverse rest-pose joint transforms
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
            for name in ("part_joints", "checked", "chunk_part", "chunk_points", "chunk_joints",
                         "chunk_weights", "chunk_mask", "chunk_used", "chunk_center",
                         "chunk_radius", "rest_inverse", "part_center",
                         "part_radius", "part_pieces", "planes", "piece_box"):
                a = getattr(self, name)
                out[name] = torch.as_tensor(a, device=device,
                                            dtype=dtype if a.dtype.kind == "f" else None)
            if (self.rest_inverse[:, :3, :3] == np.eye(3)).all():  # joints carry no rest rotation
                out["rest_shift"] = out["rest_inverse"][:, :3, 3].contiguous()
            cache[key] = out
        return cache[key]


_models: weakref.WeakKeyDictionary[BodyModel, dict[tuple, CollisionModel]] = \
    weakref.WeakKeyDictionary()
#: Points per broad-phase chunk.
CHUNK_SIZE = 24
#: Candidates are the points within this many broad-phase margins of a piece: points move
#: between refreshes, and until the next one the optimiser re-evaluates only candidates.
_POINT_SLACK = 2.0


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
    weights = np.asarray(body.skin_weights, dtype=np.float64)
    n_parts = len(vols.part_names)
    chunks: list[tuple[int, np.ndarray, np.ndarray]] = []  # (part, rest points, weights)
    for i, j in enumerate(vols.part_joints):
        verts = np.flatnonzero(vols.vertex_parts == i)[::vertex_stride]
        corners = [pc.vertices[::vertex_stride] @ frames[j, :3, :3].T + frames[j, :3, 3]
                   for pc in vols.pieces if pc.part == i]
        pts = np.concatenate([rest[verts], *corners])
        rigid = np.zeros((len(pts) - len(verts), weights.shape[1]))
        rigid[:, j] = 1.0
        w = np.concatenate([weights[verts], rigid])
        for idx in median_cuts(pts, CHUNK_SIZE):
            chunks.append((i, pts[idx], w[idx]))
    skins = [_influences(w, CHUNK_SIZE) for _, _, w in chunks]
    n_u = max(len(j) for j, _ in skins)
    points = np.zeros((len(chunks), CHUNK_SIZE, 3))
    mask = np.zeros((len(chunks), CHUNK_SIZE), dtype=bool)
    cj = np.zeros((len(chunks), n_u), dtype=np.int64)
    used = np.zeros((len(chunks), n_u), dtype=bool)
    cw = np.zeros((len(chunks), CHUNK_SIZE, n_u))
    for h, ((_, p, _), (j, w)) in enumerate(zip(chunks, skins)):
        points[h, :len(p)], mask[h, :len(p)] = p, True
        cj[h, :len(j)], cw[h, :, :len(j)], used[h, :len(j)] = j, w, True
    per_part = [[k for k, pc in enumerate(vols.pieces) if pc.part == i] for i in range(n_parts)]
    part_pieces = np.full((n_parts, max(map(len, per_part))), -1, dtype=np.int64)
    for i, ks in enumerate(per_part):
        part_pieces[i, :len(ks)] = ks
    f_max = max(len(p.planes) for p in vols.pieces)
    planes = np.tile(np.array(_PAD_PLANE), (len(vols.pieces), f_max, 1))
    for k, pc in enumerate(vols.pieces):
        planes[k, :len(pc.planes)] = pc.planes
    chunk_s = [_sphere(p) for _, p, _ in chunks]
    part_s = [_sphere(np.concatenate([vols.pieces[k].vertices for k in ks])) for ks in per_part]
    box = lambda v: np.stack((v.min(0), v.max(0)))  # noqa: E731
    model = CollisionModel(
        groups=groups, part_names=vols.part_names, part_joints=vols.part_joints,
        part_group=part_group, checked=gchecked[part_group[:, None], part_group[None, :]],
        chunk_part=np.array([c for c, _, _ in chunks]), chunk_points=points, chunk_joints=cj,
        chunk_weights=cw, chunk_mask=mask, chunk_used=used,
        chunk_center=np.array([c for c, _ in chunk_s]),
        chunk_radius=np.array([r for _, r in chunk_s]), rest_inverse=np.linalg.inv(frames),
        part_center=np.array([c for c, _ in part_s]), part_radius=np.array([r for _, r in part_s]),
        part_pieces=part_pieces, planes=planes,
        piece_box=np.array([box(pc.vertices) for pc in vols.pieces]))
    models[key] = model
    return model


def _box_distance(q: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Euclidean distance from points q (...,3) to boxes (...,2,3) (0 inside)."""
    gap = torch.clamp(box[..., 0, :] - q, min=0) + torch.clamp(q - box[..., 1, :], min=0)
    return gap.norm(dim=-1)


@dataclass(frozen=True)
class Contacts:
    """(frame, chunk, part a, part b, piece) rows whose points may be inside the piece, and
    the same at point level: `points` (frame, chunk, point, part b, piece) rows of the points
    within the broad phase's margin of the piece (its box and its planes)."""

    t: torch.Tensor
    h: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    k: torch.Tensor
    points: "PointRows"


@dataclass(frozen=True)
class PointRows:
    """Point-piece candidate rows: what the narrow phase evaluates. Kept from a refresh
    until the next one, so the optimiser's steps in between skin and test only these points
    (not every point of a near chunk)."""

    t: torch.Tensor
    h: torch.Tensor
    n: torch.Tensor
    b: torch.Tensor
    k: torch.Tensor
    #: rows repeat a point per piece: each distinct (frame, chunk, point) is skinned once
    first: torch.Tensor
    inverse: torch.Tensor
    #: ...and each distinct (frame, chunk, point, part b) is taken to b's frame once (rows
    #: repeat it per piece of b): `part_first` indexes rows, `part_inverse` maps rows to them
    part_first: torch.Tensor
    part_inverse: torch.Tensor
    #: the distinct point of each `part_first` row
    part_point: torch.Tensor
    #: the distinct points' chunks: `chunk_first` indexes the first row of each distinct
    #: (frame, chunk), `slot` is each distinct point's row in their (Q·S) skinning matrices
    chunk_first: torch.Tensor
    slot: torch.Tensor

    @classmethod
    def of(cls, t: torch.Tensor, h: torch.Tensor, n: torch.Tensor, b: torch.Tensor,
           k: torch.Tensor, n_chunks: int, size: int, n_parts: int = 0) -> "PointRows":
        point = (t * n_chunks + h) * size + n
        first, inv = _firsts(point)
        part_first, part_inv = _firsts(point * max(n_parts, 1) + b) if n_parts \
            else (torch.arange(len(t), device=t.device), torch.arange(len(t), device=t.device))
        chunk, chunk_inv = _firsts(t[first] * n_chunks + h[first])
        return cls(t, h, n, b, k, first, inv, part_first, part_inv, inv[part_first],
                   first[chunk], chunk_inv * size + n[first])


def _firsts(key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(index of the first row of each distinct key, each row's distinct key number), the
    keys numbered in sorted order (as `torch.unique`)."""
    _, inv = torch.unique(key, return_inverse=True)
    first = torch.full((int(inv.max()) + 1 if inv.numel() else 0,), len(inv),
                       dtype=torch.long, device=inv.device).scatter_reduce(
        0, inv, torch.arange(len(inv), device=inv.device), "amin")
    return first, inv


def _take(x: torch.Tensor, lead: int, i: torch.Tensor) -> torch.Tensor:
    """x[i0, i1, ...] for the first `lead` dims of x indexed by one flat index `i` (e.g.
    t * C + b): one `index_select` on a flattened view, ~2x faster on CPU than advanced
    indexing with several index tensors, same values (on a contiguous copy: `index_select`
    on a strided view, e.g. the rotation block of (…,4,4) transforms, is ~25x slower)."""
    return x.reshape(-1, *x.shape[lead:]).contiguous().index_select(0, i)


def _blend(d: dict[str, torch.Tensor], transforms: torch.Tensor) -> torch.Tensor:
    """Skinning transforms (T,J,3,4): joint world transform times inverse rest transform."""
    shift = d.get("rest_shift")
    if shift is None:
        return transforms[..., :3, :] @ d["rest_inverse"]  # the bottom row is never used
    # the inverse rest transforms are translations: [R | R·shift + t] elementwise, the terms
    # summed in the order the 4-long matmul sums them (same bits), without a tiny-matrix bmm
    r = transforms[..., :3, :3]
    t = ((r[..., 0] * shift[:, None, 0] + r[..., 1] * shift[:, None, 1]
          ) + r[..., 2] * shift[:, None, 2]) + transforms[..., :3, 3]
    return torch.cat((r, t.unsqueeze(-1)), dim=-1)


def _chunk_joints(d: dict[str, torch.Tensor], blend: torch.Tensor, t: torch.Tensor,
                  h: torch.Tensor) -> torch.Tensor:
    """The skinning transforms (R,U,12) of chunk h's U joints at frame t."""
    j = blend.shape[1]
    cj = d["chunk_joints"]
    return _take(blend.flatten(-2), 2, (t[:, None] * j + _take(cj, 1, h)).reshape(-1)) \
        .view(len(t), cj.shape[1], 12)


def _chunk_matrices(d: dict[str, torch.Tensor], blend: torch.Tensor, t: torch.Tensor,
                    h: torch.Tensor) -> torch.Tensor:
    """Σ_u w_u A_u (R,S,12) of every point of chunk rows (frame t, chunk h)."""
    return _take(d["chunk_weights"], 1, h) @ _chunk_joints(d, blend, t, h)


def _skin(d: dict[str, torch.Tensor], blend: torch.Tensor, t: torch.Tensor,
          h: torch.Tensor, n: torch.Tensor | None = None) -> torch.Tensor:
    """World points of chunk rows (R,S,3), or of single points (R,3) when `n` is given:
    v ↦ (Σ_u w_u A_u) v over the chunk's U joints."""
    if n is None:
        m, rest = _chunk_matrices(d, blend, t, h), _take(d["chunk_points"], 1, h)  # (R,S,12)
    else:
        size = d["chunk_mask"].shape[1]
        a = _chunk_joints(d, blend, t, h)                                        # (R,U,12)
        m = (_take(d["chunk_weights"], 2, h * size + n).unsqueeze(-2) @ a).squeeze(-2)  # (R,12)
        rest = _take(d["chunk_points"], 2, h * size + n)
    m = m.unflatten(-1, (3, 4))
    return _affine(m, rest)


def _affine(m: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """m[:, :3] p + m[:, 3] for (...,3,4) m and (...,3) p, column by column: on CPU this is
    several times faster than a batched matmul of 3×3 blocks."""
    return (m[..., 0] * p[..., 0:1] + m[..., 1] * p[..., 1:2] + m[..., 2] * p[..., 2:3]
            + m[..., 3])


def _to_part(rot: torch.Tensor, trans: torch.Tensor, t: torch.Tensor, b: torch.Tensor,
             p: torch.Tensor) -> torch.Tensor:
    """World points p (R,3) or (R,S,3) in the joint frame of part b at frame t: R_bᵀ (p − t_b),
    as the row-vector product (p − t_b) R_b, row by row (see `_affine`)."""
    lead = (-1, *([1] * (p.ndim - 2)))
    i = t * rot.shape[1] + b
    r = _take(rot, 2, i).view(*lead, 3, 3)
    x = p - _take(trans, 2, i).view(*lead, 3)
    return x[..., 0:1] * r[..., 0, :] + x[..., 1:2] * r[..., 1, :] + x[..., 2:3] * r[..., 2, :]


def _row_points(d: dict[str, torch.Tensor], blend: torch.Tensor, t: torch.Tensor,
                h: torch.Tensor) -> torch.Tensor:
    """`_skin` of rows (R,S,3), each distinct (frame, chunk) once (rows repeat per piece)."""
    n_h = d["chunk_part"].shape[0]
    uniq, inv = torch.unique(t * n_h + h, return_inverse=True)
    return _skin(d, blend, uniq // n_h, uniq % n_h)[inv]


def rows_in_part(d: dict[str, torch.Tensor], transforms: torch.Tensor, rows: PointRows) -> torch.Tensor:
    """Each candidate row's skinned point (R,3) in the joint frame of its part b (each distinct
    (frame, chunk, point) skinned once): what a row's piece planes are evaluated on."""
    g = transforms[:, d["part_joints"]]
    u, v, c = rows.first, rows.part_first, rows.chunk_first
    # each distinct (frame, chunk)'s skinning matrices for all its S points, one (S,U)@(U,12)
    # product, then the points needed: a (U,12) gather per chunk instead of per point (not
    # bit-identical to `_skin` of the single points: ≤ ~2e-7 m in float32)
    m = _chunk_matrices(d, _blend(d, transforms), rows.t[c], rows.h[c])
    m = m.reshape(-1, 12).index_select(0, rows.slot).unflatten(-1, (3, 4))
    size = d["chunk_mask"].shape[1]
    world = _affine(m, _take(d["chunk_points"], 2, rows.h[u] * size + rows.n[u]))
    q = _to_part(g[..., :3, :3], g[..., :3, 3], rows.t[v], rows.b[v], world[rows.part_point])
    return q[rows.part_inverse]


def _chunk_spheres(d: dict[str, torch.Tensor],
                   blend: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame spheres (T,H,3), (T,H) that contain every skinned point of each chunk.

    With weights w ≥ 0 summing to 1, a point v = c + δ (|δ| ≤ r around the rest centre c)
    goes to Σ_u w_u A_u c + Σ_u w_u R_u δ: inside the hull of the chunk joints' images of c,
    grown by r. So the sphere needs only U transforms of one point per chunk, not the skin of
    every point; a rigid chunk (U = 1) keeps its exact rest sphere.
    """
    cj = d["chunk_joints"]
    a = blend.flatten(-2).contiguous().index_select(1, cj.reshape(-1)).view(
        blend.shape[0], *cj.shape, 3, 4)                                         # (T,H,U,3,4)
    cu = _affine(a, d["chunk_center"][:, None, :])
    used = d["chunk_used"].unsqueeze(-1)
    center = (cu * used).sum(-2) / used.sum(-2)
    spread = torch.where(used[..., 0], (cu - center.unsqueeze(-2)).norm(dim=-1), 0.0).amax(-1)
    return center, d["chunk_radius"] + spread + _SLACK


def skinned_points(model: CollisionModel, transforms: torch.Tensor) -> torch.Tensor:
    """All points (T,H,S,3) in world space (padding entries are zeros), a frame at a time."""
    d = model.tensors(transforms.dtype, transforms.device)
    blend = _blend(d, transforms)
    h = torch.arange(d["chunk_part"].shape[0], device=transforms.device)
    return torch.stack([_skin(d, blend, torch.full_like(h, t), h)
                        for t in range(transforms.shape[0])])


def contacts(model: CollisionModel, transforms: torch.Tensor, margin: float = 0.0) -> Contacts:
    """Broad phase (no gradients): chunk-piece rows with a point within `margin` of the piece.

    Level 1 tests bounding spheres of the chunks' skinned points (`_chunk_spheres`) against
    part spheres, level 2 against piece boxes in the piece's joint frame, level 3 the chunk's
    skinned points against those boxes; the exact plane test is left to `frame_energies`.
    On the CPU the compiled loop `broad.broad_phase` runs the same tests (~4x cheaper than
    the tensor version, `_contacts_torch`, which other devices keep).
    """
    if transforms.device.type != "cpu":
        return _contacts_torch(model, transforms, margin)
    return contacts_of(model, *broad_rows(model, transforms, margin))


def broad_rows(model: CollisionModel, transforms: torch.Tensor, margin: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """The compiled broad phase's raw rows (R,5) (t, h, a, b, k) and point rows (Q,5)
    (t, h, n, b, k), in frame order (CPU): `contacts` without the index arrays."""
    d = model.tensors(transforms.dtype, transforms.device)
    with torch.no_grad():
        tr = transforms.detach()
        g = tr[:, d["part_joints"]]
        a = _broad_arrays(model)
        return broad_phase(
            _blend(d, tr).double().numpy(), g[..., :3, :3].double().numpy(),
            g[..., :3, 3].double().numpy(), model.chunk_joints, model.chunk_used,
            model.chunk_center, model.chunk_radius, model.chunk_part, model.checked,
            model.part_center, model.part_radius, model.part_pieces, model.piece_box,
            model.chunk_points, model.chunk_weights, model.chunk_mask, model.planes,
            a["n_planes"], float(margin), float(margin * _POINT_SLACK), _SLACK)


def contacts_of(model: CollisionModel, rows: np.ndarray, pts: np.ndarray) -> Contacts:
    """`Contacts` of `broad_rows`' arrays (grouped by frame and chunk, in the broad phase's
    order), with `PointRows`' index arrays (`broad.index_rows`)."""
    t, h, ca, b, k = torch.from_numpy(np.ascontiguousarray(rows)).unbind(1)
    pt, ph, pn, pb, pk = (torch.from_numpy(np.ascontiguousarray(c)) for c in pts.T)
    index = index_rows(pts[:, 0].copy(), pts[:, 1].copy(), pts[:, 2].copy(), pts[:, 3].copy(),
                       model.chunk_mask.shape[1], model.part_radius.shape[0])
    return Contacts(t, h, ca, b, k, PointRows(pt, ph, pn, pb, pk,
                                              *(torch.from_numpy(a) for a in index)))


def _broad_arrays(model: CollisionModel) -> dict[str, np.ndarray]:
    """What `broad_phase` needs beyond the model's own arrays (cached on the model)."""
    cache = model.__dict__.setdefault("_broad", {})
    if not cache:
        cache["n_planes"] = (model.planes[..., 3] != _PAD_PLANE[3]).sum(1).astype(np.int64)
    return cache


def _contacts_torch(model: CollisionModel, transforms: torch.Tensor, margin: float = 0.0
                    ) -> Contacts:
    """`contacts` as tensor operations (the GPU's broad phase; the CPU's reference)."""
    d = model.tensors(transforms.dtype, transforms.device)
    with torch.no_grad():
        g = transforms[:, d["part_joints"]]
        rot, trans = g[..., :3, :3], g[..., :3, 3]
        blend = _blend(d, transforms)
        chunk_c, chunk_r = _chunk_spheres(d, blend)                             # (T,H,3), (T,H)
        part_c = (rot @ d["part_center"].unsqueeze(-1)).squeeze(-1) + trans      # (T,C,3)
        ca = d["chunk_part"]
        reach = chunk_r[..., None] + d["part_radius"] + margin
        near = (torch.cdist(chunk_c, part_c) < reach) & d["checked"][ca]
        ft, fh, fb = torch.nonzero(near, as_tuple=True)
        pieces = d["part_pieces"][fb]                                            # (M,K)
        cq = _to_part(rot, trans, ft, fb, chunk_c[ft, fh])
        pk = pieces.clamp(min=0)
        close = _box_distance(cq[:, None, :], d["piece_box"][pk])
        close = (close < chunk_r[ft, fh, None] + margin) & (pieces >= 0)
        m, ks = torch.nonzero(close, as_tuple=True)
        t, h, a, b, k = ft[m], fh[m], ca[fh[m]], fb[m], pk[m, ks]
        if m.numel():  # level 3: the chunk's points against the piece's box, then its planes
            # each distinct (frame, chunk, part b) once: rows repeat it per piece of b
            first, inv = _firsts((t * d["chunk_part"].shape[0] + h) * rot.shape[1] + b)
            q = _to_part(rot, trans, t[first], b[first],
                         _row_points(d, blend, t[first], h[first]))[inv]
            box = _box_distance(q, d["piece_box"].index_select(0, k)[:, None])
            hit = ((box <= margin) & d["chunk_mask"][h]).any(dim=1)
            wide = margin * _POINT_SLACK
            r, n = torch.nonzero((box <= wide) & d["chunk_mask"][h] & hit[:, None], as_tuple=True)
            # max over a convex piece's planes is a lower bound of the distance outside it
            f, _ = _piece_planes(model, d, k[r], q[r, n])
            r, n = r[f <= wide], n[f <= wide]
            return Contacts(t[hit], h[hit], a[hit], b[hit], k[hit],
                            PointRows.of(t[r], h[r], n, b[r], k[r], *d["chunk_mask"].shape,
                                         d["part_radius"].shape[0]))
    return Contacts(t, h, a, b, k, PointRows.of(t, h, h, b, k, *d["chunk_mask"].shape))


def frame_energies(model: CollisionModel, transforms: torch.Tensor, tolerance: float = 0.0,
                   near: Contacts | None = None) -> torch.Tensor:
    """Per-frame Σ_v max(0, −f − tolerance)² (T,) from joint world transforms (T,J,4,4).

    A negative tolerance also penalises points within −tolerance outside a piece (the
    optimiser's clearance target).

    `near` reuses a broad phase computed earlier with a margin (the optimiser refreshes it
    every few steps); by default it is computed here, exactly. The deepest piece and plane of
    each penetrating point are picked without gradients; the gradient of a max is that of its
    argmax, so recomputing just that plane (and that point's skin) with autograd gives the
    exact gradient at a cost that follows the penetrating points only.
    """
    t_frames = transforms.shape[0]
    zero = transforms.new_zeros(t_frames) + 0.0 * transforms[:, :1, 0, 0].sum()
    sel = penetrations(model, transforms, tolerance, near)
    if sel is None:
        return zero
    depth = torch.relu(point_depths(model, transforms, sel) - tolerance)
    return zero.index_add(0, sel.t, depth * depth)


def frame_energies_and_exact(model: CollisionModel, transforms: torch.Tensor, tolerance: float,
                             exact_tolerance: float, near: Contacts
                             ) -> tuple[torch.Tensor, torch.Tensor]:
    """`frame_energies` at `tolerance` (differentiable) and, without gradients, at a larger
    `exact_tolerance`, from one narrow phase.

    Why: the optimiser's refresh steps needed both (the clearance objective and the clear
    test), and each `penetrations` pass re-skins every candidate row. A point's deepest piece
    is the same at either tolerance when it is deeper than `exact_tolerance` (the minimum over
    a superset of rows that reaches below it), so the exact energy is the selection's rows
    with f < −exact_tolerance, each the same depth, added in the same order: the same values
    as `frame_energies(model, transforms, exact_tolerance, near)`."""
    if exact_tolerance < tolerance:
        raise ValueError("exact_tolerance must be ≥ tolerance (its rows are a subset)")
    t_frames = transforms.shape[0]
    zero = transforms.new_zeros(t_frames) + 0.0 * transforms[:, :1, 0, 0].sum()
    exact = transforms.new_zeros(t_frames)
    sel = penetrations(model, transforms, tolerance, near)
    if sel is None:
        return zero, exact
    signed = point_depths(model, transforms, sel)
    depth = torch.relu(signed - tolerance)
    with torch.no_grad():
        inside = torch.nonzero(sel.f < -exact_tolerance).squeeze(1)
        deep = torch.relu(signed.detach()[inside] - exact_tolerance)
        exact = exact.index_add(0, sel.t[inside], deep * deep)
    return zero.index_add(0, sel.t, depth * depth), exact


@dataclass(frozen=True)
class Penetrations:
    """Penetrating points: (frame, chunk, point, part b) and the deepest piece's active plane
    (Q,4) in part b's joint frame (one row per point and part it is inside)."""

    t: torch.Tensor
    h: torch.Tensor
    n: torch.Tensor
    b: torch.Tensor
    plane: torch.Tensor
    #: the active plane's value (−depth, no gradients) as the selection measured it
    f: torch.Tensor | None = None


def penetrations(model: CollisionModel, transforms: torch.Tensor, tolerance: float = 0.0,
                 near: Contacts | None = None) -> Penetrations | None:
    """Which points are deeper than `tolerance` inside which part, and by which plane (no
    gradients); None when none is. `point_depths` evaluates them (differentiably)."""
    d = model.tensors(transforms.dtype, transforms.device)
    reach = max(0.0, -tolerance)
    c = contacts(model, transforms, reach) if near is None else near
    if c.t.numel() == 0:
        return None
    p = c.points
    if p.t.numel() == 0:
        return None
    if transforms.dtype == torch.float32 and transforms.device.type == "cpu":
        return _penetrations_compiled(model, d, transforms, tolerance, reach, p)
    return _penetrations_torch(model, d, transforms, tolerance, reach, p)


def _penetrations_torch(model: CollisionModel, d: dict[str, torch.Tensor],
                        transforms: torch.Tensor, tolerance: float, reach: float,
                        p: PointRows) -> Penetrations | None:
    """`penetrations`' selection as tensor operations (GPU, float64; the float32 CPU path's
    reference)."""
    with torch.no_grad():
        q = rows_in_part(d, transforms, p)
        r = torch.nonzero(_box_distance(q, d["piece_box"].index_select(0, p.k)) <= reach).squeeze(1)
        f, plane = _piece_planes(model, d, p.k[r], q[r])
        inside = torch.nonzero(f < -tolerance).squeeze(1)
        if inside.numel() == 0:
            return None
        r, f, plane = r[inside], f[inside], plane[inside]
        # a part's SDF is the min over its pieces: keep the deepest piece per (frame, point, part)
        keep = deepest_per_point(d, p.t[r], p.h[r], p.n[r], p.b[r], f)
        rk = r[keep]
        return Penetrations(p.t[rk], p.h[rk], p.n[rk], p.b[rk], d["planes"][p.k[rk], plane[keep]],
                            f[keep])


def _penetrations_compiled(model: CollisionModel, d: dict[str, torch.Tensor],
                           transforms: torch.Tensor, tolerance: float, reach: float,
                           p: PointRows) -> Penetrations | None:
    """`penetrations`' selection as one compiled pass (`narrow.select`), float32 on the CPU:
    the same rows, planes and values as the tensor version (see `narrow`)."""
    with torch.no_grad():
        tr = transforms.detach()
        if "rest_shift" in d:  # the same float32 bits as below, in one compiled pass
            blend, rot, trans = select_inputs(tr.contiguous().numpy(), d["rest_shift"].numpy(),
                                              model.part_joints)
        else:
            g = tr[:, d["part_joints"]]
            blend = _blend(d, tr)
            blend = blend.reshape(*blend.shape[:2], 12).contiguous().numpy()
            rot, trans = g[..., :3, :3].contiguous().numpy(), g[..., :3, 3].contiguous().numpy()
        rows, arg, f = select(
            blend, rot, trans,
            model.chunk_joints, d["chunk_weights"].numpy(), d["chunk_points"].numpy(),
            d["piece_box"].numpy(), d["planes"].numpy(), _broad_arrays(model)["n_planes"],
            p.t.numpy(), p.h.numpy(), p.n.numpy(), p.b.numpy(), p.k.numpy(), p.first.numpy(),
            p.part_first.numpy(), p.part_inverse.numpy(), p.part_point.numpy(),
            np.float32(reach), np.float32(tolerance), d["part_radius"].shape[0])
    if len(rows) == 0:
        return None
    r = torch.from_numpy(rows)
    k = p.k[r]
    return Penetrations(p.t[r], p.h[r], p.n[r], p.b[r], d["planes"][k, torch.from_numpy(arg)],
                        torch.from_numpy(f))


def deepest_per_point(d: dict[str, torch.Tensor], t: torch.Tensor, h: torch.Tensor, n: torch.Tensor,
                      b: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Indices of the rows with the least `f` (the deepest piece) per (frame, chunk, point, part):
    a part's signed distance is the minimum over its convex pieces."""
    n_chunks, n_parts = d["chunk_part"].shape[0], d["part_radius"].shape[0]
    size = d["chunk_mask"].shape[1]
    key = ((t * n_chunks + h) * size + n) * n_parts + b
    # per key (in sorted key order) the least f, ties to the lowest row: what a stable sort by
    # f then by key picked first, with one sort instead of two
    _, inv = torch.unique(key, return_inverse=True)
    k = int(inv.max()) + 1 if inv.numel() else 0
    least = torch.full((k,), float("inf"), dtype=f.dtype, device=f.device) \
        .scatter_reduce(0, inv, f, "amin")
    tied = torch.nonzero(f == least[inv]).squeeze(1)
    return torch.full((k,), len(f), dtype=torch.long, device=f.device) \
        .scatter_reduce(0, inv[tied], tied, "amin")


def _piece_planes(model: CollisionModel, d: dict[str, torch.Tensor], k: torch.Tensor,
                  q: torch.Tensor, own: list[torch.Tensor] | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """max_f(n_f·q + d_f) and its plane index per row (points q (R,3) in the frame of piece
    k (R,)), one small matmul per piece with its own planes: gathering the padded (R,F,4)
    planes per row cost more than the arithmetic. `own` replaces each piece's planes (a
    subset of them, as `solve` uses)."""
    if q.is_cuda and own is None and len(k):
        # one batched product over the padded planes: on a GPU the per-piece loop below is
        # bound by kernel launches (padding planes have d = -1e9, never the max)
        pl = d["planes"][k]                                                     # (R,F,4)
        vals = torch.baddbmm(pl[..., 3:4], pl[..., :3], q.unsqueeze(-1)).squeeze(-1)
        return vals.max(-1)
    f = q.new_empty(len(k))
    arg = torch.empty(len(k), dtype=torch.long, device=k.device)
    if len(k) == 0:
        return f, arg
    pieces, order = torch.sort(k, stable=True)
    ids, counts = torch.unique_consecutive(pieces, return_counts=True)
    own = _own_planes(model, d) if own is None else own
    start = 0
    for piece, n in zip(ids.tolist(), counts.tolist()):
        rows = order[start:start + n]
        start += n
        pl = own[piece]
        fr, ar = torch.addmm(pl[:, 3], q[rows], pl[:, :3].T).max(-1)
        f[rows], arg[rows] = fr, ar
    return f, arg


def _own_planes(model: CollisionModel, d: dict[str, torch.Tensor]) -> list[torch.Tensor]:
    """Each piece's planes without the padding (cached per dtype/device like `tensors`)."""
    planes = d["planes"]
    cache = model.__dict__.setdefault("_own_planes", {})
    key = (planes.dtype, planes.device)
    if key not in cache:
        real = (model.planes[..., 3] != _PAD_PLANE[3]).sum(1)
        cache[key] = [planes[i, :int(n)].contiguous() for i, n in enumerate(real)]
    return cache[key]


def point_depths(model: CollisionModel, transforms: torch.Tensor,
                 sel: Penetrations, frame_offset: torch.Tensor | None = None) -> torch.Tensor:
    """Signed depth (Q,) of the selected points behind their active plane (positive inside),
    differentiable in `transforms`. `frame_offset` (Q,) shifts the frame index (a batch of
    perturbed copies of the motion stacked along frames)."""
    t = sel.t if frame_offset is None else sel.t + frame_offset
    if transforms.device.type == "cpu":  # compiled, hand-written gradient (`narrow.PointDepths`)
        arrays = (model.rest_inverse, model.part_joints, model.chunk_joints, model.chunk_weights,
                  model.chunk_points, t.numpy(), sel.h.numpy(), sel.n.numpy(), sel.b.numpy(),
                  sel.plane.detach().double().numpy())
        return PointDepths.apply(transforms, arrays)
    d = model.tensors(transforms.dtype, transforms.device)
    g = transforms[:, d["part_joints"]]
    rot, trans = g[..., :3, :3], g[..., :3, 3]
    blend = _blend(d, transforms)
    ql = _to_part(rot, trans, t, sel.b, _skin(d, blend, t, sel.h, sel.n))
    nd = sel.plane.to(transforms.dtype)
    return -(ql * nd[:, :3]).sum(-1) - nd[:, 3]


def energy(model: CollisionModel, transforms: torch.Tensor, tolerance: float = 0.0) -> torch.Tensor:
    """L_col (Eq. 1): mean over frames of the per-frame energies."""
    return frame_energies(model, transforms, tolerance).mean()


def pose_frame_energies(body: BodyModel, pose: torch.Tensor, betas: torch.Tensor,
                        model: CollisionModel, tolerance: float = 0.0) -> torch.Tensor:
    """Per-frame energies (T,) of a (T,55,3) pose tensor (differentiable in pose)."""
    return frame_energies(model, body.joint_transforms(pose, betas.to(pose)), tolerance)
