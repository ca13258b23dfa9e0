"""Penetration depth of the skinned mesh: an evaluation measure independent of the optimiser.

The optimiser minimises an energy over convex pieces and a vertex subsample; this module judges
its result on the full skinned mesh (every vertex, every triangle) and shares nothing with it
but the collision groups and the checked-pair matrix (`exclusions`).

Per frame, the depth is the largest distance by which a vertex of one group lies inside the
surface of another group it is checked against. How:

1. *Solids.* The mesh is split into connected components. mannequin-x's wooden mesh is 29
   separate wooden segments, every one watertight (split by dominant skinning weight instead,
   only 10 of its 19 part submeshes are: a part boundary cuts segments open), so a component
   is a closed surface and inside/outside is exact. A component is a *solid* when it is
   watertight and spans at most `MAX_SOLID_GROUPS` groups (a whole-body skin such as SMPL-X is
   one component that self-intersects where an arm enters the chest; it is split into open
   per-group *patches* instead, see below).
2. *Broad phase.* Per frame, component boxes; only pairs of components that hold a checked
   pair of groups and whose boxes overlap go on.
3. *Crossing triangles.* The two components' triangles inside the boxes' overlap, tested
   pairwise (a box sweep, then separating axes; the same pairs as python-fcl's BVHs): without
   a crossing pair of triangles the two surfaces do not interpenetrate and the pair scores 0
   (a component wholly inside another, never crossing, is not counted; it cannot arise in
   continuous motion without crossing first). This also keeps any sign error below
   from turning clear frames into false depth.
4. *Signed depth.* For each vertex of one component inside the overlap box, the closest point
   on the other solid (exact: nearest triangle centroids, widened until no farther triangle can
   be closer), signed by the angle-weighted pseudo-normal of the closest feature (face, edge or
   vertex; Bærentzen & Aanæs 2005), which is exact for a closed manifold. An inside vertex
   counts when its group and the closest triangle's group are a checked pair; the depth is its
   distance to the surface.

Patches (non-solid components): a vertex is tested against the triangles of each group it is
checked against within its own component, signed by the pseudo-normal of the whole component.
Where the closest point lies on the patch's border (the seam to an unchecked group) the sign is
not trusted and the vertex is not counted: near seams this may undercount, never overcount.
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.collision import frame_kernels
from embody.collision.closest import build_grid, crossing_pairs, grid_nearest
from embody.collision.exclusions import checked_pairs, part_groups

#: A watertight component spanning more groups than this is a skin, not a rigid segment.
MAX_SOLID_GROUPS = 3
#: Frames skinned per batch.
_BATCH = 64


@dataclass(frozen=True)
class _Component:
    vertices: np.ndarray        # (n,) global vertex ids
    faces: np.ndarray           # (m,3) local vertex ids
    face_group: np.ndarray      # (m,)
    edge_of_face: np.ndarray    # (m,3) edge id of face edges (v0v1, v1v2, v2v0)
    edge_faces: np.ndarray      # (E,2) faces of each edge, -1 for a border edge
    solid: bool
    nbr_ptr: np.ndarray         # (n+1,) CSR vertex adjacency (local ids)
    nbr_idx: np.ndarray

    def neighbours(self, idx: np.ndarray) -> np.ndarray:
        """The sorted one-ring of the vertices `idx` (one CSR gather, no per-vertex slices)."""
        if len(idx) == 0:
            return idx
        start = self.nbr_ptr[idx]
        count = self.nbr_ptr[idx + 1] - start
        pos = np.arange(int(count.sum())) + np.repeat(start - (np.cumsum(count) - count), count)
        return np.unique(self.nbr_idx[pos])


@dataclass(frozen=True)
class DepthMesh:
    """A triangle mesh split into components, with vertex groups and the checked group pairs."""

    faces: np.ndarray           # (F,3)
    vertex_group: np.ndarray    # (V,)
    checked: np.ndarray         # (G,G) bool
    components: tuple[_Component, ...]
    vertex_component: np.ndarray  # (V,)

    @classmethod
    def build(cls, faces: np.ndarray, vertex_group: np.ndarray, checked: np.ndarray,
              max_solid_groups: int = MAX_SOLID_GROUPS) -> "DepthMesh":
        faces = np.asarray(faces, dtype=np.int64)
        vertex_group = np.asarray(vertex_group, dtype=np.int64)
        n_v = len(vertex_group)
        label = _components(faces, n_v)
        comps = []
        face_comp = label[faces[:, 0]]
        for c in range(label.max() + 1):
            fc = faces[face_comp == c]
            if len(fc) == 0:  # vertices in no face
                continue
            verts, local = np.unique(fc, return_inverse=True)
            local = local.reshape(-1, 3)
            counts = np.bincount(vertex_group[verts])
            fg = _face_groups(vertex_group[verts][local])
            eof, ef, watertight = _edges(local)
            e = np.concatenate([local[:, [0, 1]], local[:, [1, 2]], local[:, [2, 0]]])
            e = np.unique(np.concatenate([e, e[:, ::-1]]), axis=0)
            ptr = np.searchsorted(e[:, 0], np.arange(len(verts) + 1))
            comps.append(_Component(verts, local, fg, eof, ef,
                                    watertight and int((counts > 0).sum()) <= max_solid_groups,
                                    ptr, e[:, 1].copy()))
        return cls(faces, vertex_group, np.asarray(checked, dtype=bool), tuple(comps), label)


def _components(faces: np.ndarray, n_v: int) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_v, n_v))
    return connected_components(g, directed=False)[1]


def _face_groups(groups: np.ndarray) -> np.ndarray:
    """Majority group of each face's three vertices (the first vertex's on a three-way tie)."""
    a, b, c = groups.T
    return np.where((b == c) & (a != b), b, a)


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    e = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 1)   # (m,3,2)
    key = np.sort(e, -1).reshape(-1, 2)
    uniq, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    edge_faces = np.full((len(uniq), 2), -1, dtype=np.int64)
    face_of = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(inv, kind="stable")
    first = np.ones(len(order), dtype=bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    edge_faces[inv[order][first], 0] = face_of[order][first]
    second = ~first
    edge_faces[inv[order][second], 1] = face_of[order][second]
    watertight = bool((counts == 2).all())
    return inv.reshape(-1, 3), edge_faces, watertight


_meshes: weakref.WeakKeyDictionary[BodyModel, dict[tuple, DepthMesh]] = \
    weakref.WeakKeyDictionary()
#: Judged frames per body: digest of (pairs, device kind, betas, pose) → depth (m).
_memo: weakref.WeakKeyDictionary[BodyModel, OrderedDict[bytes, float]] = \
    weakref.WeakKeyDictionary()
_memo_lock = threading.Lock()
#: Frames remembered per body (16-byte keys: ~10 MB at most).
_MEMO_SIZE = 100_000


def depth_mesh(body: BodyModel, allow_pairs: Iterable[Sequence[str]] = ()) -> DepthMesh:
    """The body's skinned mesh with collision groups by dominant skinning weight (cached)."""
    allow = tuple(tuple(p) for p in allow_pairs)
    cache = _meshes.setdefault(body, {})
    if allow not in cache:
        groups, part_group = part_groups(body.part_names)
        checked = checked_pairs(groups, body.joint_names, body.parents, allow)
        cache[allow] = DepthMesh.build(np.asarray(body.faces),
                                       part_group[np.asarray(body.vertex_parts)], checked)
    return cache[allow]


# -- geometry ------------------------------------------------------------------------------------
def _normals(v: np.ndarray, comp: _Component) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(face normals (m,3), edge pseudo-normals (E,3), angle-weighted vertex normals (n,3))."""
    tri = v[comp.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    ef = comp.edge_faces
    en = n[ef[:, 0]] + np.where(ef[:, 1:] >= 0, n[np.maximum(ef[:, 1], 0)], 0.0)
    vn = np.zeros((len(v), 3))
    for k in range(3):
        e1 = tri[:, (k + 1) % 3] - tri[:, k]
        e2 = tri[:, (k + 2) % 3] - tri[:, k]
        cos = (e1 * e2).sum(1) / np.maximum(np.linalg.norm(e1, axis=1)
                                             * np.linalg.norm(e2, axis=1), 1e-300)
        np.add.at(vn, comp.faces[:, k], np.arccos(np.clip(cos, -1, 1))[:, None] * n)
    return n, en, vn


class _Surface:
    """One component (or one group's faces of it) posed in one frame, for closest-point queries."""

    def __init__(self, v: np.ndarray, comp: _Component, face_ids: np.ndarray,
                 normals: tuple[np.ndarray, np.ndarray, np.ndarray]):
        self.v, self.comp, self.face_ids = v, comp, face_ids
        self.tri = v[comp.faces[face_ids]]                                     # (m,3,3)
        self.centroid = self.tri.mean(1)
        self.radius = np.linalg.norm(self.tri - self.centroid[:, None], axis=2).max(1)
        self.reach = float(self.radius.max())
        # the exact nearest-triangle search's grid (cells about two mean triangle radii wide)
        self.grid = build_grid(self.centroid, max(2.0 * float(self.radius.mean()), 1e-6))
        self.normals = normals
        # each triangle's plane (face normal n, offset n·a) and how far its other corners lie
        # off it (0 up to rounding; large for a sliver whose normal is unreliable)
        self.plane = normals[0][face_ids]
        self.offset = (self.plane * self.tri[:, 0]).sum(1)
        self.slack = np.maximum(np.abs((self.plane * self.tri[:, 1]).sum(1) - self.offset),
                                np.abs((self.plane * self.tri[:, 2]).sum(1) - self.offset))

    def query(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(distance, signed side (<0 inside), face id (component-local), on-border) per point.

        Exact closest triangle (`closest.grid_nearest`: a ring search on a centroid grid that
        skips a triangle only when a lower bound on its distance exceeds the best found; the
        least distance wins, the lowest triangle index among equal ones)."""
        n = len(p)
        dist, point = np.empty(n), np.empty((n, 3))
        feat, which = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
        lo, dims, cell, start, order = self.grid
        grid_nearest(np.ascontiguousarray(p, dtype=np.float64), self.tri, self.centroid,
                     self.radius, self.reach, self.plane, self.offset, self.slack, lo, dims,
                     cell, start, order, dist, point, feat, which)
        face = self.face_ids[which]
        fn, en, vn = self.normals
        gf = self.comp.faces[face]
        eof = self.comp.edge_of_face[face]
        normal = fn[face]
        for code in range(3):
            m = feat == code
            normal[m] = vn[gf[m, code]]
        border = np.zeros(len(p), dtype=bool)
        # a whole watertight component has no border edge (no seam, no hole)
        whole = self.comp.solid and len(self.face_ids) == len(self.comp.faces)
        for code in range(3):
            m = feat == 3 + code
            e = eof[m, code]
            normal[m] = en[e]
            if not whole:
                border[m] = ~np.isin(self.comp.edge_faces[e], self.face_ids).all(1)
        side = ((p - point) * normal).sum(1)
        return dist, side, face, border


def _crossing(va: np.ndarray, fa: np.ndarray, vb: np.ndarray,
              fb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Crossing (intersecting or touching) triangle pairs of (va, fa) and (vb, fb) as indices
    into fa and fb (`closest.crossing_pairs`: box sweep and separating-axis tests, compiled;
    the same pairs as python-fcl's BVH collide, `tests/test_depth_exact.py`, ~7x faster
    without the per-call BVH builds)."""
    if len(fa) == 0 or len(fb) == 0:
        none = np.zeros(0, dtype=np.int64)
        return none, none
    return crossing_pairs(np.ascontiguousarray(va, dtype=np.float64),
                          np.ascontiguousarray(fa, dtype=np.int64),
                          np.ascontiguousarray(vb, dtype=np.float64),
                          np.ascontiguousarray(fb, dtype=np.int64))


def _checked_comp_pairs(mesh: DepthMesh) -> list[tuple[int, int]]:
    groups = [np.unique(mesh.vertex_group[c.vertices]) for c in mesh.components]
    pairs = []
    for i in range(len(groups)):
        for j in range(i + 1, len(groups)):
            if mesh.checked[np.ix_(groups[i], groups[j])].any():
                pairs.append((i, j))
    return pairs


def _flood(mesh: DepthMesh, v: np.ndarray, comp: _Component, seeds: np.ndarray,
           surf: _Surface, trust_border: bool, allowed: np.ndarray | None = None) -> float:
    """Deepest vertex of `comp` inside `surf` whose group is checked against the closest
    triangle's group. Every inside region of a surface is bounded by triangles that cross the
    other surface, so a flood over inside vertices from those triangles' vertices finds all of
    them while testing only the inside vertices and their one-ring."""
    seen = np.zeros(len(comp.vertices), dtype=bool)
    if allowed is not None:
        seen |= ~allowed
    frontier = seeds[~seen[seeds]]
    best = 0.0
    groups = mesh.vertex_group[comp.vertices]
    while len(frontier):
        seen[frontier] = True
        dist, side, face, border = surf.query(v[comp.vertices[frontier]])
        inside = side < 0
        if not trust_border:
            inside &= ~border
        ok = inside & mesh.checked[groups[frontier], surf.comp.face_group[face]]
        if ok.any():
            best = max(best, float(dist[ok].max()))
        nb = comp.neighbours(frontier[inside])
        frontier = nb[~seen[nb]]
    return best


def _separated(va: np.ndarray, vb: np.ndarray) -> bool:
    """A plane normal to the line between the two point sets' centroids separates them: then
    no triangle spanned by the one crosses one spanned by the other (a sound, cheap test that
    spares the BVH build for pairs whose boxes overlap but whose surfaces are apart)."""
    axis = vb.mean(0) - va.mean(0)
    return bool((va @ axis).max() < (vb @ axis).min())


def _component_boxes(mesh: DepthMesh, v: np.ndarray) -> np.ndarray:
    """(...,C,2,3) min/max corner of each component of posed meshes (...,V,3)."""
    order, starts = _component_order(mesh)
    w = v[..., order, :]
    return np.stack([np.minimum.reduceat(w, starts, axis=-2),
                     np.maximum.reduceat(w, starts, axis=-2)], axis=-2)


def _component_order(mesh: DepthMesh) -> tuple[np.ndarray, np.ndarray]:
    cache = mesh.__dict__.setdefault("_order", [])
    if not cache:
        sizes = [len(c.vertices) for c in mesh.components]
        cache.extend((np.concatenate([c.vertices for c in mesh.components]),
                      np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)))
    return cache[0], cache[1]


def frame_depth_reference(mesh: DepthMesh, v: np.ndarray,
                          pairs: list[tuple[int, int]] | None = None,
                          box: np.ndarray | None = None) -> float:
    """Max penetration depth (m) of one posed mesh (V,3), all in NumPy: the reference the
    compiled `frame_depths` keeps the bits of (tests, benchmarks). `pairs` limits the
    component pairs tested (default: every checked pair); `box` (C,2,3) the components'
    boxes if known."""
    pairs = _checked_comp_pairs(mesh) if pairs is None else pairs
    comps = mesh.components
    box = _component_boxes(mesh, v) if box is None else box
    cache: dict[int, tuple] = {}
    fbox: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    surfaces: dict[int, _Surface] = {}

    def normals(i: int) -> tuple:
        if i not in cache:
            cache[i] = _normals(v[comps[i].vertices], comps[i])
        return cache[i]

    def faces_in_box(i: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        if i not in fbox:  # each component's face boxes once per frame, not once per pair
            vc = v[comps[i].vertices]
            a, b, c = (vc[comps[i].faces[:, k]] for k in range(3))
            fbox[i] = (np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c))
        fmin, fmax = fbox[i]
        return np.flatnonzero(((fmax >= lo) & (fmin <= hi)).all(-1))

    def within(i: int, si: np.ndarray, j: int, sj: np.ndarray) -> np.ndarray:
        if len(si) == 0 or len(sj) == 0:
            return si[:0]
        lo, hi = fbox[j][0][sj].min(0), fbox[j][1][sj].max(0)
        return si[((fbox[i][1][si] >= lo) & (fbox[i][0][si] <= hi)).all(-1)]

    best = 0.0
    for i, j in pairs:
        lo, hi = np.maximum(box[i, 0], box[j, 0]), np.minimum(box[i, 1], box[j, 1])
        if (lo > hi).any():
            continue
        ci, cj = comps[i], comps[j]
        vi, vj = v[ci.vertices], v[cj.vertices]
        si, sj = faces_in_box(i, lo, hi), faces_in_box(j, lo, hi)
        # only faces of a group checked against some face of the other side can matter
        si = si[mesh.checked[ci.face_group[si]][:, np.unique(cj.face_group[sj])].any(1)]
        sj = sj[mesh.checked[cj.face_group[sj]][:, np.unique(ci.face_group[si])].any(1)]
        # a crossing triangle's box meets its partner's, so it meets the box of the other
        # side's remaining triangles: shrink both sides to that (fewer triangles per BVH)
        si = within(i, si, j, sj)
        sj = within(j, sj, i, si)
        if len(si) == 0 or len(sj) == 0 or _separated(vi[np.unique(ci.faces[si])],
                                                      vj[np.unique(cj.faces[sj])]):
            continue
        xi, xj = _crossing(vi, ci.faces[si], vj, cj.faces[sj])
        xi, xj = si[xi], sj[xj]
        keep = mesh.checked[ci.face_group[xi], cj.face_group[xj]]
        if not keep.any():  # crossing only where contact is expected (e.g. at a joint)
            continue
        xi, xj = xi[keep], xj[keep]
        for a, seeds, b in ((ci, np.unique(ci.faces[xi]), j), (cj, np.unique(cj.faces[xj]), i)):
            c = comps[b]
            if not c.solid:
                continue
            if b not in surfaces:  # one surface (and k-d tree) per component and frame
                surfaces[b] = _Surface(v[c.vertices], c, np.arange(len(c.faces)), normals(b))
            surf = surfaces[b]
            allowed = mesh.checked[mesh.vertex_group[a.vertices]][:, np.unique(c.face_group)]
            best = max(best, _flood(mesh, v, a, seeds, surf, trust_border=True,
                                    allowed=allowed.any(1)))
    for i, c in enumerate(comps):  # skins: group against group inside one component
        if not c.solid:
            best = max(best, _skin_depth(mesh, v, i, normals(i)))
    return best


def _skin_depth(mesh: DepthMesh, v: np.ndarray, i: int, normals: tuple) -> float:
    """Deepest vertex of the non-solid component i of the posed mesh v (V,3) inside a patch of
    its own (one group's faces) that its group is checked against (module docstring)."""
    c = mesh.components[i]
    best = 0.0
    vc = v[c.vertices]
    vgroup = mesh.vertex_group[c.vertices]
    for g in np.unique(c.face_group):
        faces_g = np.flatnonzero(c.face_group == g)
        allowed = mesh.checked[vgroup, g]
        f_other = np.flatnonzero(mesh.checked[c.face_group, g])
        if not allowed.any() or len(f_other) == 0:
            continue
        xg, xo = _crossing(vc, c.faces[faces_g], vc, c.faces[f_other])
        if len(xg) == 0:
            continue
        xo = np.unique(xo)
        surf = _Surface(vc, c, faces_g, normals)
        best = max(best, _flood(mesh, v, c, np.unique(c.faces[f_other[xo]]), surf,
                                trust_border=False, allowed=allowed))
    return best


def frame_depths_reference(mesh: DepthMesh, vertices: np.ndarray) -> np.ndarray:
    """Max penetration depth (m) per frame of posed meshes (T,V,3), all in NumPy (the
    reference of `frame_depths`). The component boxes and their overlaps are computed for all
    frames at once; each frame then visits only its checked pairs whose boxes overlap (a pair
    whose boxes are apart cannot cross)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    pairs = np.array(_checked_comp_pairs(mesh), dtype=np.int64).reshape(-1, 2)
    boxes = _component_boxes(mesh, vertices)                               # (T,C,2,3)
    lo = np.maximum(boxes[:, pairs[:, 0], 0], boxes[:, pairs[:, 1], 0])
    hi = np.minimum(boxes[:, pairs[:, 0], 1], boxes[:, pairs[:, 1], 1])
    overlap = (lo <= hi).all(-1)                                           # (T,P)
    return np.array([frame_depth_reference(mesh, v, [tuple(p) for p in pairs[o].tolist()], b)
                     for v, o, b in zip(vertices, overlap, boxes)])


@dataclass(frozen=True)
class _Flat:
    """A DepthMesh as flat arrays for `frame_kernels` (built once per mesh): component c's
    vertices are verts[vptr[c]:vptr[c+1]], its faces faces[fptr[c]:fptr[c+1]] (local vertex
    ids; gfaces the global ones), its edges efaces[eptr[c]:eptr[c+1]] (local face ids), its
    one-ring CSR nptr[vptr[c]+c : vptr[c+1]+c+1] into nidx (local vertex ids)."""

    vptr: np.ndarray
    verts: np.ndarray
    vgroup: np.ndarray
    fptr: np.ndarray
    faces: np.ndarray
    gfaces: np.ndarray
    fgroup: np.ndarray
    eof: np.ndarray
    eptr: np.ndarray
    efaces: np.ndarray
    nptr: np.ndarray
    nidx: np.ndarray
    solid: np.ndarray
    checked: np.ndarray
    allowed: np.ndarray     # (C,G): group g is checked against some face group of component c
    pairs: np.ndarray       # (P,2) component pairs holding a checked pair of groups
    skins: tuple[int, ...]  # the non-solid components
    slot_ptr: np.ndarray    # (C+1,) component c's face groups are slots slot_ptr[c]:slot_ptr[c+1]
    slot_group: np.ndarray  # (S,) a slot's face group
    slot_vptr: np.ndarray   # (S+1,) a slot's vertices (global ids, of its group's faces) are
    slot_verts: np.ndarray  #        slot_verts[slot_vptr[s]:slot_vptr[s+1]]

    @classmethod
    def of(cls, mesh: DepthMesh) -> "_Flat":
        cache = mesh.__dict__.setdefault("_flat", [])
        if not cache:
            comps = mesh.components
            size = lambda xs: np.r_[0, np.cumsum([len(x) for x in xs])].astype(np.int64)
            nbase = size([c.nbr_idx for c in comps])
            checked = np.ascontiguousarray(mesh.checked, dtype=np.bool_)
            allowed = np.zeros((len(comps), len(checked)), dtype=np.bool_)
            for k, c in enumerate(comps):
                allowed[k] = checked[:, np.unique(c.face_group)].any(1)
            cat = lambda xs, dtype=np.int64: np.ascontiguousarray(np.concatenate(xs), dtype=dtype)
            slots = [(g, np.unique(c.vertices[c.faces[c.face_group == g]]))
                     for c in comps for g in np.unique(c.face_group)]
            cache.append(cls(
                vptr=size([c.vertices for c in comps]),
                verts=cat([c.vertices for c in comps]),
                vgroup=cat([mesh.vertex_group[c.vertices] for c in comps]),
                fptr=size([c.faces for c in comps]),
                faces=cat([c.faces for c in comps]),
                gfaces=cat([c.vertices[c.faces] for c in comps]),
                fgroup=cat([c.face_group for c in comps]),
                eof=cat([c.edge_of_face for c in comps]),
                eptr=size([c.edge_faces for c in comps]),
                efaces=cat([c.edge_faces for c in comps]),
                nptr=cat([c.nbr_ptr + nbase[k] for k, c in enumerate(comps)]),
                nidx=cat([c.nbr_idx for c in comps]),
                solid=np.array([c.solid for c in comps], dtype=np.bool_),
                checked=checked, allowed=allowed,
                pairs=np.array(_checked_comp_pairs(mesh), dtype=np.int64).reshape(-1, 2),
                skins=tuple(k for k, c in enumerate(comps) if not c.solid),
                slot_ptr=size([np.unique(c.face_group) for c in comps]),
                slot_group=np.array([g for g, _ in slots], dtype=np.int64),
                slot_vptr=size([v for _, v in slots]),
                slot_verts=cat([v for _, v in slots])))
        return cache[0]


def frame_depths(mesh: DepthMesh, vertices: np.ndarray) -> np.ndarray:
    """Max penetration depth (m) per frame of posed meshes (T,V,3): `frame_depths_reference`'s
    depths, bit for bit, with the solids' per-frame work compiled (`frame_kernels`: three
    compiled calls and one `np.arccos` per batch); skins (non-solid components) in NumPy."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    f = _Flat.of(mesh)
    jf, ja, js, sptr, seeds, sf, sc = frame_kernels.broad_phase(
        vertices, f.vptr, f.verts, f.fptr, f.faces, f.gfaces, f.fgroup, f.solid, f.checked,
        f.pairs, f.slot_ptr, f.slot_group, f.slot_vptr, f.slot_verts)
    cos, cptr = frame_kernels.corner_cosines(vertices, f.fptr, f.gfaces, sf, sc)
    best = frame_kernels.floods(
        vertices, f.vptr, f.verts, f.vgroup, f.fptr, f.faces, f.gfaces, f.fgroup, f.eof,
        f.eptr, f.efaces, f.nptr, f.nidx, f.checked, f.allowed, sf, sc, np.arccos(cos), cptr,
        jf, ja, js, sptr, seeds)
    for i in f.skins:
        c = mesh.components[i]
        for t, v in enumerate(vertices):
            best[t] = max(best[t], _skin_depth(mesh, v, i, _normals(v[c.vertices], c)))
    return best


def frame_depth(mesh: DepthMesh, v: np.ndarray) -> float:
    """Max penetration depth (m) of one posed mesh (V,3) (`frame_depths` of one frame)."""
    return float(frame_depths(mesh, np.asarray(v, dtype=np.float64)[None])[0])


def motion_depths(body: BodyModel, pose: np.ndarray, betas: np.ndarray,
                  allow_pairs: Iterable[Sequence[str]] = (),
                  device: torch.device | str = "cpu") -> np.ndarray:
    """Per-frame max penetration depth (m) of the body's skinned mesh over a pose (T,55,3).
    The skinning runs on `device` (float64); the mesh tests always on the CPU.

    A frame judged before (same body, pose, betas, pairs and device kind: the collide step
    judges the input, then the changed frames, then the pull-back's probes, which repeat some
    frames) is answered from a memo; the depth is a deterministic function of those, so the
    memo returns the same bits."""
    mesh = depth_mesh(body, allow_pairs)
    pose = np.asarray(pose, dtype=np.float64)
    betas_np = np.asarray(betas, dtype=np.float64)
    salt = repr((tuple(tuple(p) for p in allow_pairs), torch.device(device).type)).encode()
    salt += betas_np.tobytes()
    keys = [hashlib.blake2b(salt + np.ascontiguousarray(f).tobytes(), digest_size=16).digest()
            for f in pose]
    with _memo_lock:
        memo = _memo.setdefault(body, OrderedDict())
        known = [memo.get(k) for k in keys]
    todo = np.array([i for i, d in enumerate(known) if d is None], dtype=np.int64)
    out = np.array([0.0 if d is None else d for d in known])
    if len(todo):
        b = torch.as_tensor(betas_np, dtype=torch.float64, device=device)
        parts = []
        with torch.no_grad():
            for s in range(0, len(todo), _BATCH):
                x = torch.as_tensor(pose[todo[s:s + _BATCH]], dtype=torch.float64,
                                    device=device)
                parts.append(frame_depths(mesh, body.vertices_array(x, b)))
        out[todo] = np.concatenate(parts)
        with _memo_lock:
            for i in todo.tolist():
                memo[keys[i]] = float(out[i])
            while len(memo) > _MEMO_SIZE:
                memo.popitem(last=False)
    return out


def depth_metrics(before: np.ndarray, after: np.ndarray) -> dict[str, float | int]:
    """Before/after: frames deeper than 2 mm and 5 mm, max depth (mm), median depth (mm) of the
    frames that penetrate at all (> 0; NaN-free: 0 when none)."""
    out: dict[str, float | int] = {}
    for tag, d in (("before", before), ("after", after)):
        mm = np.asarray(d, dtype=np.float64) * 1e3
        pen = mm[mm > 0]
        out[f"frames_over_2mm_{tag}"] = int((mm > 2.0).sum())
        out[f"frames_over_5mm_{tag}"] = int((mm > 5.0).sum())
        out[f"max_depth_mm_{tag}"] = float(mm.max()) if len(mm) else 0.0
        out[f"median_depth_mm_{tag}"] = float(np.median(pen)) if len(pen) else 0.0
    return out
