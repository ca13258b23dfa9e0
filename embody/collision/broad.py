"""Compiled (numba) broad phase of the collision energy (`energy.contacts` on the CPU).

Why: the optimiser refreshes its candidate rows every `refresh_every` steps, and in torch that
refresh was ~40 % of `optimize._optimise` (s11-adamspeed): tens of small tensor ops over
(frame, chunk, part) pairs, most of them far apart. Here the same three levels run as one loop
per frame, each chunk skinned once and taken to a part's frame once, so only the pairs that
pass a level cost anything at the next.

The tests are the torch broad phase's (`energy._contacts_torch`, kept for GPUs), in the same
order, with the same strict/non-strict comparisons, in float64 arithmetic: every level is a
conservative bound with a margin of centimetres, so rounding can move a row only at that
margin, where no point reaches a piece before the next refresh (`tests/test_collision_energy.py`
checks the rows against the torch broad phase).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _grow(a: np.ndarray, n: int) -> np.ndarray:
    """`a` with room for row n (doubled when full)."""
    if n < a.shape[0]:
        return a
    b = np.empty((2 * a.shape[0], a.shape[1]), dtype=a.dtype)
    b[:a.shape[0]] = a
    return b


@njit(cache=True, nogil=True)
def _box_distance2(x: float, y: float, z: float, box: np.ndarray) -> float:
    """The squared distance from (x, y, z) to `box` (2,3) (its root: the distance)."""
    gx = max(box[0, 0] - x, 0.0) + max(x - box[1, 0], 0.0)
    gy = max(box[0, 1] - y, 0.0) + max(y - box[1, 1], 0.0)
    gz = max(box[0, 2] - z, 0.0) + max(z - box[1, 2], 0.0)
    return gx * gx + gy * gy + gz * gz


#: Relative band around a squared limit within which `_below` takes the root.
_BAND = 1e-10


@njit(cache=True, nogil=True, inline="always")
def _below(d2: float, limit: float, strict: bool) -> bool:
    """sqrt(d2) < limit (`strict`) or ≤ limit, the float64 comparison's answer, with the root
    taken only within a relative 1e-10 of the limit.

    Why: the broad phase compares ~10⁴ chunk-part distances a frame, nearly all far beyond
    their limit, and the square root was most of a comparison. Outside the band the answer
    cannot depend on rounding (sqrt and the products round by ~1e-16 relative)."""
    if limit > 0.0:
        l2 = limit * limit
        if d2 > l2 * (1.0 + _BAND):
            return False
        if d2 < l2 * (1.0 - _BAND):
            return True
    root = np.sqrt(d2)
    return root < limit if strict else root <= limit


@njit(cache=True, nogil=True)
def broad_phase(blend: np.ndarray, rot: np.ndarray, trans: np.ndarray,
                chunk_joints: np.ndarray, chunk_used: np.ndarray, chunk_center: np.ndarray,
                chunk_radius: np.ndarray, chunk_part: np.ndarray, checked: np.ndarray,
                part_center: np.ndarray, part_radius: np.ndarray, part_pieces: np.ndarray,
                piece_box: np.ndarray, chunk_points: np.ndarray, chunk_weights: np.ndarray,
                chunk_mask: np.ndarray, planes: np.ndarray, n_planes: np.ndarray,
                margin: float, wide: float, slack: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows (t, h, a, b, k) of chunk h (part a) at frame t with a point within `margin` of the
    box of piece k (of part b), and point rows (t, h, n, b, k) of those rows' points within
    `wide` of the box whose plane bound (max over the piece's planes) is within `wide` too.

    `blend` (T,J,3,4) skinning transforms, `rot`/`trans` (T,C,3,3)/(T,C,3) the parts' joint
    transforms; the rest as in `energy.CollisionModel`, `n_planes` (P,) each piece's real
    planes. Rows come in the torch broad phase's order: frame, chunk, part, piece slot, point."""
    n_t, n_c = rot.shape[0], rot.shape[1]
    n_h, n_u = chunk_joints.shape
    n_s = chunk_points.shape[1]
    n_k = part_pieces.shape[1]
    rows = np.empty((256, 5), dtype=np.int64)
    pts = np.empty((1024, 5), dtype=np.int64)
    nr = 0
    npt = 0
    cc = np.empty((n_h, 3))
    cr = np.empty(n_h)
    cu = np.empty((n_u, 3))
    pc = np.empty((n_c, 3))
    world = np.empty((n_s, 3))
    local = np.empty((n_s, 3))
    box = np.empty(n_s)
    close = np.empty(n_k, dtype=np.int64)
    m = np.empty((3, 4))
    for t in range(n_t):
        # level 1: spheres around each chunk's skinned points (see `energy._chunk_spheres`)
        for h in range(n_h):
            x0, x1, x2 = chunk_center[h, 0], chunk_center[h, 1], chunk_center[h, 2]
            s0 = s1 = s2 = 0.0
            used = 0
            for u in range(n_u):
                if chunk_used[h, u]:
                    a = blend[t, chunk_joints[h, u]]
                    cu[u, 0] = a[0, 0] * x0 + a[0, 1] * x1 + a[0, 2] * x2 + a[0, 3]
                    cu[u, 1] = a[1, 0] * x0 + a[1, 1] * x1 + a[1, 2] * x2 + a[1, 3]
                    cu[u, 2] = a[2, 0] * x0 + a[2, 1] * x1 + a[2, 2] * x2 + a[2, 3]
                    s0 += cu[u, 0]
                    s1 += cu[u, 1]
                    s2 += cu[u, 2]
                    used += 1
            cc[h, 0], cc[h, 1], cc[h, 2] = s0 / used, s1 / used, s2 / used
            spread = 0.0
            for u in range(n_u):
                if chunk_used[h, u]:
                    d0, d1, d2 = cu[u, 0] - cc[h, 0], cu[u, 1] - cc[h, 1], cu[u, 2] - cc[h, 2]
                    spread = max(spread, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
            cr[h] = chunk_radius[h] + spread + slack
        for c in range(n_c):
            r = rot[t, c]
            for i in range(3):
                pc[c, i] = (r[i, 0] * part_center[c, 0] + r[i, 1] * part_center[c, 1]
                            + r[i, 2] * part_center[c, 2] + trans[t, c, i])
        for h in range(n_h):
            a_part = chunk_part[h]
            skinned = False
            for b in range(n_c):
                if not checked[a_part, b]:
                    continue
                d0, d1, d2 = cc[h, 0] - pc[b, 0], cc[h, 1] - pc[b, 1], cc[h, 2] - pc[b, 2]
                if not _below(d0 * d0 + d1 * d1 + d2 * d2, cr[h] + part_radius[b] + margin, True):
                    continue
                # level 2: the chunk's sphere centre in b's frame against b's piece boxes
                r = rot[t, b]
                e0, e1, e2 = cc[h, 0] - trans[t, b, 0], cc[h, 1] - trans[t, b, 1], \
                    cc[h, 2] - trans[t, b, 2]
                q0 = e0 * r[0, 0] + e1 * r[1, 0] + e2 * r[2, 0]
                q1 = e0 * r[0, 1] + e1 * r[1, 1] + e2 * r[2, 1]
                q2 = e0 * r[0, 2] + e1 * r[1, 2] + e2 * r[2, 2]
                n_close = 0
                for ks in range(n_k):
                    k = part_pieces[b, ks]
                    if k >= 0 and _below(_box_distance2(q0, q1, q2, piece_box[k]),
                                         cr[h] + margin, True):
                        close[n_close] = k
                        n_close += 1
                if n_close == 0:
                    continue
                # level 3: the chunk's skinned points (once per frame and chunk) in b's frame
                if not skinned:
                    skinned = True
                    for n in range(n_s):
                        m[:] = 0.0
                        for u in range(n_u):
                            w = chunk_weights[h, n, u]
                            if w != 0.0:
                                a = blend[t, chunk_joints[h, u]]
                                for i in range(3):
                                    for j in range(4):
                                        m[i, j] += w * a[i, j]
                        p = chunk_points[h, n]
                        for i in range(3):
                            world[n, i] = m[i, 0] * p[0] + m[i, 1] * p[1] + m[i, 2] * p[2] + m[i, 3]
                tb = trans[t, b]
                for n in range(n_s):
                    e0, e1, e2 = world[n, 0] - tb[0], world[n, 1] - tb[1], world[n, 2] - tb[2]
                    local[n, 0] = e0 * r[0, 0] + e1 * r[1, 0] + e2 * r[2, 0]
                    local[n, 1] = e0 * r[0, 1] + e1 * r[1, 1] + e2 * r[2, 1]
                    local[n, 2] = e0 * r[0, 2] + e1 * r[1, 2] + e2 * r[2, 2]
                for i in range(n_close):
                    k = close[i]
                    hit = False
                    for n in range(n_s):
                        if chunk_mask[h, n]:
                            box[n] = _box_distance2(local[n, 0], local[n, 1], local[n, 2],
                                                    piece_box[k])  # squared
                            hit = hit or _below(box[n], margin, False)
                    if not hit:
                        continue
                    rows = _grow(rows, nr)
                    rows[nr, 0], rows[nr, 1], rows[nr, 2] = t, h, a_part
                    rows[nr, 3], rows[nr, 4] = b, k
                    nr += 1
                    for n in range(n_s):
                        if not chunk_mask[h, n] or not _below(box[n], wide, False):
                            continue
                        # max over a convex piece's planes: a lower bound of the distance outside
                        f = -np.inf
                        for j in range(n_planes[k]):
                            pl = planes[k, j]
                            f = max(f, pl[0] * local[n, 0] + pl[1] * local[n, 1]
                                    + pl[2] * local[n, 2] + pl[3])
                        if f <= wide:
                            pts = _grow(pts, npt)
                            pts[npt, 0], pts[npt, 1], pts[npt, 2] = t, h, n
                            pts[npt, 3], pts[npt, 4] = b, k
                            npt += 1
    return rows[:nr], pts[:npt]


@njit(cache=True, nogil=True, inline="always")
def _sort_small(a: np.ndarray, n: int) -> None:
    """Sort a[:n] in place (insertion sort: a group's few keys; `np.sort` allocated a copy
    per group, most of `index_rows`' time)."""
    for i in range(1, n):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v


@njit(cache=True, nogil=True)
def index_rows(t: np.ndarray, h: np.ndarray, n: np.ndarray, b: np.ndarray, size: int,
               n_parts: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                      np.ndarray, np.ndarray, np.ndarray]:
    """`energy.PointRows.of`'s index arrays (first, inverse, part_first, part_inverse,
    part_point, chunk_first, slot: what `torch.unique` numbering in sorted key order gives)
    for rows grouped by (frame, chunk) in increasing order, as the broad phase emits them:
    each group's keys are numbered on their own, in one pass."""
    n_rows = len(t)
    first = np.empty(n_rows, dtype=np.int64)
    inverse = np.empty(n_rows, dtype=np.int64)
    part_first = np.empty(n_rows, dtype=np.int64)
    part_inverse = np.empty(n_rows, dtype=np.int64)
    part_point = np.empty(n_rows, dtype=np.int64)
    chunk_first = np.empty(n_rows, dtype=np.int64)
    slot = np.empty(n_rows, dtype=np.int64)
    point_row = np.full(size, -1, dtype=np.int64)       # a group's first row of each point n
    point_id = np.empty(size, dtype=np.int64)
    pair_row = np.full(size * n_parts, -1, dtype=np.int64)  # ... of each (n, b)
    pair_id = np.empty(size * n_parts, dtype=np.int64)
    keys = np.empty(n_rows, dtype=np.int64)
    n_pts = n_pairs = n_groups = 0
    s = 0
    while s < n_rows:
        e = s
        while e < n_rows and t[e] == t[s] and h[e] == h[s]:
            e += 1
        n_keys = 0
        for r in range(s, e):
            if point_row[n[r]] < 0:
                point_row[n[r]] = r
            kb = n[r] * n_parts + b[r]
            if pair_row[kb] < 0:
                pair_row[kb] = r
                keys[n_keys] = kb
                n_keys += 1
        g_first = n_pts
        for m in range(size):  # points in increasing n
            if point_row[m] >= 0:
                point_id[m] = n_pts
                first[n_pts] = point_row[m]
                slot[n_pts] = n_groups * size + m
                n_pts += 1
        chunk_first[n_groups] = first[g_first]
        n_groups += 1
        _sort_small(keys, n_keys)
        for kb in keys[:n_keys]:  # (point, part) pairs in increasing (n, b)
            pair_id[kb] = n_pairs
            part_first[n_pairs] = pair_row[kb]
            part_point[n_pairs] = point_id[kb // n_parts]
            n_pairs += 1
        for r in range(s, e):
            inverse[r] = point_id[n[r]]
            part_inverse[r] = pair_id[n[r] * n_parts + b[r]]
        for r in range(s, e):  # reset the group's tables
            point_row[n[r]] = -1
            pair_row[n[r] * n_parts + b[r]] = -1
        s = e
    return (first[:n_pts], inverse, part_first[:n_pairs], part_inverse, part_point[:n_pairs],
            chunk_first[:n_groups], slot[:n_pts])
