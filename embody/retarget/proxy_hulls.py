"""The IK's sphere/hull proxy contacts (`Residuals._collision`): which (frame, sphere/hull pair)
are within the margin, their signed clearance, contact point and normal, as one compiled pass.

Why: the NumPy form (`hull_contacts_numpy`, kept as the reference the tests hold the compiled one
to) ran four broad phases as many small operations on (groups, 3, members) arrays and a Python
loop over hulls: ~1.4 ms a call, a quarter of the IK's CPU time. `hull_contacts` does the same
tests per (frame, group, member) in one numba loop:

1. a part's bounding sphere against its hull's bounding sphere (`group_reach`);
2. that sphere against the hull's box, in the hull body's frame (`group_box_reach`);
3. each member sphere's centre against the box grown by margin + its radius (`member_reach`);
4. the polytope's signed distance: the largest of the hull's plane distances (its `np.unique`d
   plane set, in that order; the first of equal maxima gives the normal, as `argmax` does).

The arithmetic follows the NumPy form's operation order (IEEE float64, no fast-math); NumPy's
3×3 matmuls may go through BLAS (FMA), so the two agree to round-off, not bit for bit. Both return
the contacts sorted by frame, then pair: the IK's row layout."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from embody.robot.fk import rotate


@dataclass
class HullTables:
    """The broad-phase tables of the sphere/hull pairs (built once per robot and config by
    `Residuals`). A group is the pairs of one sphere body against one hull; FK body indices
    are columns of the FK pass's (T,B,...) arrays."""

    part_body: np.ndarray  # (P,) FK body of each part (a body carrying paired spheres)
    part_centre: np.ndarray  # (P,3) its bounding sphere's centre, body frame
    hull_body: np.ndarray  # (H,) FK body of each hull
    hull_centre: np.ndarray  # (H,3) the hull's bounding sphere centre, body frame
    group_part: np.ndarray  # (G,) part of each group
    group_hull: np.ndarray  # (G,) hull of each group
    group_reach: np.ndarray  # (G,) part radius + hull radius + margin
    group_box_reach: np.ndarray  # (G,) part radius + margin
    group_members: np.ndarray  # (G,M) pair indices, −1 = padding
    member_centres_t: np.ndarray  # (G,3,M) member spheres' centres, sphere-body frame
    member_reach_t: np.ndarray  # (G,3,M) box half size + margin + radius (−inf on padding)
    box_mid: np.ndarray  # (H,3) hull box centre, hull-body frame
    box_half: np.ndarray  # (H,3) hull box half size
    hull_planes: list[np.ndarray]  # per hull (F_h,4), unpadded (`np.unique`d) n·x + d
    plane_table: np.ndarray  # (H,F,4) the same padded with zeros (read up to `plane_count`)
    plane_count: np.ndarray  # (H,)
    pair_sphere: np.ndarray  # (Q,) sphere of each pair
    pair_hull: np.ndarray  # (Q,) hull of each pair
    pair_radius: np.ndarray  # (Q,) its sphere's radius


def plane_table(planes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-hull plane sets (F_h,4) in one zero-padded (H,F,4) array and their counts (H,)."""
    count = np.array([len(p) for p in planes], dtype=np.int64)
    table = np.zeros((len(planes), max(int(count.max(initial=0)), 1), 4))
    for h, p in enumerate(planes):
        table[h, : len(p)] = p
    return table, count


Contacts = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def hull_contacts(tab: HullTables, rot: np.ndarray, pos: np.ndarray, margin: float) -> Contacts:
    """Sphere/hull pairs with clearance < margin in the FK pass rot (T,B,3,3), pos (T,B,3):
    frame (C,), pair (C,), clearance (C,), contact point x (C,3) and hull normal (C,3) in the
    torso frame, sorted by frame then pair."""
    return _hull_contacts(np.ascontiguousarray(rot, dtype=np.float64), np.ascontiguousarray(pos, dtype=np.float64),
                          tab.part_body, tab.part_centre, tab.hull_body, tab.hull_centre,
                          tab.group_part, tab.group_hull, tab.group_reach, tab.group_box_reach,
                          tab.group_members, tab.member_centres_t, tab.member_reach_t,
                          tab.box_mid, tab.box_half, tab.plane_table, tab.plane_count,
                          tab.pair_radius, float(margin))


@njit(cache=True, nogil=True, error_model="numpy")
def _hull_contacts(rot, pos, part_body, part_centre, hull_body, hull_centre, group_part, group_hull,
                   group_reach, group_box_reach, members, centres_t, reach_t, box_mid, box_half,
                   planes, plane_count, pair_radius, margin):  # pragma: no cover (compiled)
    t_n, n_part, n_hull, n_group, n_mem = rot.shape[0], len(part_body), len(hull_body), len(group_part), \
        members.shape[1]
    cap = 64
    tc = np.empty(cap, np.int64)
    qc = np.empty(cap, np.int64)
    value = np.empty(cap)
    x = np.empty((cap, 3))
    normal = np.empty((cap, 3))
    n = 0
    pc = np.empty((n_part, 3))
    hc = np.empty((n_hull, 3))
    rel = np.empty((3, 3))
    p_rel = np.empty(3)
    xl = np.empty(3)
    v = np.empty(3)
    for t in range(t_n):
        start = n
        # bounding-sphere centres, torso frame: pos + rotate(rot, c)
        for p in range(n_part):
            b = part_body[p]
            for a in range(3):
                pc[p, a] = pos[t, b, a] + (rot[t, b, a, 0] * part_centre[p, 0] + rot[t, b, a, 1] * part_centre[p, 1]
                                           + rot[t, b, a, 2] * part_centre[p, 2])
        for h in range(n_hull):
            b = hull_body[h]
            for a in range(3):
                hc[h, a] = pos[t, b, a] + (rot[t, b, a, 0] * hull_centre[h, 0] + rot[t, b, a, 1] * hull_centre[h, 1]
                                           + rot[t, b, a, 2] * hull_centre[h, 2])
        for g in range(n_group):
            p, h = group_part[g], group_hull[g]
            g0, g1, g2 = pc[p, 0] - hc[h, 0], pc[p, 1] - hc[h, 1], pc[p, 2] - hc[h, 2]
            if not g0 ** 2 + g1 ** 2 + g2 ** 2 < group_reach[g] ** 2:
                continue
            hb, sb = hull_body[h], part_body[p]
            # the part's sphere against the hull's box, hull-body frame: r_hᵀ (pc − p_h)
            for a in range(3):
                v[a] = pc[p, a] - pos[t, hb, a]
            out = 0.0
            for a in range(3):
                c = rot[t, hb, 0, a] * v[0] + rot[t, hb, 1, a] * v[1] + rot[t, hb, 2, a] * v[2]
                out = max(out, max(abs(c - box_mid[h, a]) - box_half[h, a], 0.0))
            if not out < group_box_reach[g]:
                continue
            # the sphere body in the hull body's frame: r_hᵀ r_b, r_hᵀ (p_b − p_h)
            for a in range(3):
                for c in range(3):
                    rel[a, c] = (rot[t, hb, 0, a] * rot[t, sb, 0, c] + rot[t, hb, 1, a] * rot[t, sb, 1, c]
                                 + rot[t, hb, 2, a] * rot[t, sb, 2, c])
                v[a] = pos[t, sb, a] - pos[t, hb, a]
            for a in range(3):
                p_rel[a] = rot[t, hb, 0, a] * v[0] + rot[t, hb, 1, a] * v[1] + rot[t, hb, 2, a] * v[2]
            for m in range(n_mem):
                q = members[g, m]
                if q < 0:
                    continue
                inside = True
                for a in range(3):  # the first axis outside decides
                    xl[a] = (rel[a, 0] * centres_t[g, 0, m] + rel[a, 1] * centres_t[g, 1, m]
                             + rel[a, 2] * centres_t[g, 2, m]) + p_rel[a]
                    if not abs(xl[a] - box_mid[h, a]) - reach_t[g, a, m] < 0:
                        inside = False
                        break
                if not inside:
                    continue
                best, face, radius = -np.inf, 0, pair_radius[q]
                for f in range(plane_count[h]):
                    sd = (xl[0] * planes[h, f, 0] + xl[1] * planes[h, f, 1] + xl[2] * planes[h, f, 2]) + planes[h, f, 3]
                    if f == 0 or sd > best:
                        best, face = sd, f
                val = best - radius
                if not val < margin:
                    continue
                if n == cap:  # grow the output
                    cap *= 2
                    tc, qc, value = _grow1(tc, cap), _grow1(qc, cap), _grow1(value, cap)
                    x, normal = _grow2(x, cap), _grow2(normal, cap)
                tc[n], qc[n], value[n] = t, q, val
                for a in range(3):
                    x[n, a] = (rot[t, hb, a, 0] * xl[0] + rot[t, hb, a, 1] * xl[1] + rot[t, hb, a, 2] * xl[2]) \
                        + pos[t, hb, a]
                    normal[n, a] = (rot[t, hb, a, 0] * planes[h, face, 0] + rot[t, hb, a, 1] * planes[h, face, 1]
                                    + rot[t, hb, a, 2] * planes[h, face, 2])
                n += 1
        if n - start > 1:  # this frame's contacts by pair (each pair once a frame)
            order = np.argsort(qc[start:n]) + start
            qc[start:n] = qc[order]
            value[start:n] = value[order]
            x[start:n] = x[order]
            normal[start:n] = normal[order]
    return tc[:n].copy(), qc[:n].copy(), value[:n].copy(), x[:n].copy(), normal[:n].copy()


@njit(cache=True, nogil=True)
def _grow1(a, cap):  # pragma: no cover (compiled)
    out = np.empty(cap, a.dtype)
    out[: len(a)] = a
    return out


@njit(cache=True, nogil=True)
def _grow2(a, cap):  # pragma: no cover (compiled)
    out = np.empty((cap, a.shape[1]), a.dtype)
    out[: len(a)] = a
    return out


def hull_contacts_numpy(tab: HullTables, rot: np.ndarray, pos: np.ndarray, margin: float) -> Contacts:
    """`hull_contacts` in NumPy (the reference: the IK's form before the compiled kernel)."""
    pb, hb = tab.part_body, tab.hull_body
    # broad phase per (body part, hull) on bounding spheres ...
    pc = pos[:, pb] + rotate(rot[:, pb], tab.part_centre)
    hc = pos[:, hb] + rotate(rot[:, hb], tab.hull_centre)
    gv = pc[:, tab.group_part] - hc[:, tab.group_hull]
    tg, gg = np.nonzero(gv[..., 0] ** 2 + gv[..., 1] ** 2 + gv[..., 2] ** 2 < tab.group_reach**2)
    # ... then the part's bounding sphere against the hull's box, in the hull body's frame ...
    h_of = tab.group_hull[gg]
    r_h, p_h = rot[tg, hb[h_of]], pos[tg, hb[h_of]]
    r_ht = np.swapaxes(r_h, 1, 2)
    centre_l = np.einsum("gba,gb->ga", r_h, pc[tg, tab.group_part[gg]] - p_h)
    out = np.maximum(np.abs(centre_l - tab.box_mid[h_of]) - tab.box_half[h_of], 0.0)
    # per axis, so exactly the groups with no member passing the per-point test below go
    keep = out.max(1) < tab.group_box_reach[gg]
    tg, gg, h_of, r_h, p_h, r_ht = tg[keep], gg[keep], h_of[keep], r_h[keep], p_h[keep], r_ht[keep]
    # ... then per point against the hull's box ...
    gb = pb[tab.group_part[gg]]
    r_rel = r_ht @ rot[tg, gb]
    p_rel = rotate(r_ht, pos[tg, gb] - p_h)
    members = tab.group_members[gg]  # (G,M), −1 = padding
    xl = r_rel @ tab.member_centres_t[gg] + p_rel[..., None]  # (G,3,M), hull-body frame
    d = np.abs(xl - tab.box_mid[h_of][..., None]) - tab.member_reach_t[gg]
    inside = np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2]) < 0
    gsel, msel = np.nonzero(inside)
    tc, qc, xl = tg[gsel], members[gsel, msel], xl[gsel, :, msel]
    r_h, p_h = r_h[gsel], p_h[gsel]
    # ... then the polytope's plane distances, hull by hull (no padded plane sets)
    hi = tab.pair_hull
    value, normal_l = np.empty(len(qc)), np.empty((len(qc), 3))
    order = np.argsort(hi[qc], kind="stable")
    hulls, starts = np.unique(hi[qc][order], return_index=True)
    for h, idx in zip(hulls, np.split(order, starts[1:])):
        planes = tab.hull_planes[h]
        sd = xl[idx] @ planes[:, :3].T + planes[:, 3]
        face = sd.argmax(1)
        value[idx] = sd[np.arange(len(idx)), face]
        normal_l[idx] = planes[face, :3]
    value -= tab.pair_radius[qc]
    sel = np.flatnonzero(value < margin)
    sel = sel[np.lexsort((qc[sel], tc[sel]))]  # by frame, then pair: a stable row layout
    r_h = r_h[sel]
    return tc[sel], qc[sel], value[sel], rotate(r_h, xl[sel]) + p_h[sel], rotate(r_h, normal_l[sel])


def max_planes(xl: np.ndarray, hull: np.ndarray, table: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: the largest plane distance n·x + d over its hull's planes (the polytope's signed
    distance) and that plane's normal (the first of equal maxima, as `argmax`). Points xl (N,3) in
    their hull's frame, hull (N,) rows of a `plane_table` (H,F,4) read up to `count` (H,). The
    narrow phase of `hull_contacts`, for callers with their own broad phase
    (`hand_clearance.HandClearanceTerm.rows`); `max_planes_numpy` is its NumPy form."""
    return _max_planes(np.ascontiguousarray(xl, dtype=np.float64), np.ascontiguousarray(hull, dtype=np.int64),
                       table, count)


@njit(cache=True, nogil=True)
def _max_planes(xl, hull, planes, plane_count):  # pragma: no cover (compiled)
    n = len(xl)
    value = np.empty(n)
    normal = np.empty((n, 3))
    for i in range(n):
        h = hull[i]
        best, face = -np.inf, 0
        for f in range(plane_count[h]):
            sd = (xl[i, 0] * planes[h, f, 0] + xl[i, 1] * planes[h, f, 1] + xl[i, 2] * planes[h, f, 2]) + planes[h, f, 3]
            if f == 0 or sd > best:
                best, face = sd, f
        value[i] = best
        for a in range(3):
            normal[i, a] = planes[h, face, a]
    return value, normal


def max_planes_numpy(xl: np.ndarray, hull: np.ndarray, planes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """`max_planes` in NumPy, hull by hull (the reference; `planes`: per hull its (F_h,4) set)."""
    value, normal = np.empty(len(xl)), np.empty((len(xl), 3))
    order = np.argsort(hull, kind="stable")
    present, starts = np.unique(hull[order], return_index=True)
    for h, idx in zip(present, np.split(order, starts[1:])):
        sd = xl[idx] @ planes[h][:, :3].T + planes[h][:, 3]
        face = sd.argmax(-1)
        value[idx] = sd[np.arange(len(idx)), face]
        normal[idx] = planes[h][face, :3]
    return value, normal

