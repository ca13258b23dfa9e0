"""Compiled (numba) kernels of the mesh judge (`depth`): the exact closest triangle, and crossing
triangle pairs.

Why: after s9-judge the judge's time went to `_Surface.query` (a k-d tree k-nearest + ball scan,
~30 µs a point in small NumPy operations) and to `_crossing` (a python-fcl BVH built per
component pair and frame). Here:

- `grid_nearest`: a ring search on a grid of triangle centroids; a triangle is skipped only when
  a lower bound on its distance exceeds the best found, ties go to the lowest triangle index
  (what the k-d tree scan's stable sort picked), and the per-triangle formula is the NumPy
  judge's Ericson closest point operation for operation (IEEE float64, no fast-math, sums in
  NumPy's order; `tests/test_depth_exact.py` keeps that form as the reference), so the judge's
  depths keep their bits.
- `crossing_pairs`: a box sweep and a separating-axis test; the same pairs as fcl's BVH collide.

`error_model="numpy"`: a 0/0 on a degenerate triangle is NaN as in NumPy, not an exception."""

from __future__ import annotations

import numpy as np
from numba import njit

#: Most grid cells along one axis (`build_grid`).
MAX_CELLS = 64


@njit(cache=True, nogil=True, error_model="numpy")
def _dot(x0: float, x1: float, x2: float, y0: float, y1: float, y2: float) -> float:
    return x0 * y0 + x1 * y1 + x2 * y2


@njit(cache=True, nogil=True, error_model="numpy")
def _corner(out: np.ndarray, x: np.ndarray, feature: int) -> int:
    out[0], out[1], out[2] = x[0], x[1], x[2]
    return feature


@njit(cache=True, nogil=True, error_model="numpy")
def _on_edge(out: np.ndarray, x: np.ndarray, e0: float, e1: float, e2: float, t: float,
             feature: int) -> int:
    out[0], out[1], out[2] = x[0] + e0 * t, x[1] + e1 * t, x[2] + e2 * t
    return feature


@njit(cache=True, nogil=True, error_model="numpy")
def closest_point(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                  out: np.ndarray) -> int:
    """Closest point on triangle abc to p, written into `out` (3,); returns the feature:
    0,1,2 vertex a,b,c; 3,4,5 edge ab, bc, ca; 6 face (the region precedence of
    NumPy judge's: a, b, ab, c, ca, bc, face)."""
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ac0, ac1, ac2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    ap0, ap1, ap2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    d1 = _dot(ab0, ab1, ab2, ap0, ap1, ap2)
    d2 = _dot(ac0, ac1, ac2, ap0, ap1, ap2)
    bp0, bp1, bp2 = p[0] - b[0], p[1] - b[1], p[2] - b[2]
    d3 = _dot(ab0, ab1, ab2, bp0, bp1, bp2)
    d4 = _dot(ac0, ac1, ac2, bp0, bp1, bp2)
    cp0, cp1, cp2 = p[0] - c[0], p[1] - c[1], p[2] - c[2]
    d5 = _dot(ab0, ab1, ab2, cp0, cp1, cp2)
    d6 = _dot(ac0, ac1, ac2, cp0, cp1, cp2)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if d1 <= 0 and d2 <= 0:
        return _corner(out, a, 0)
    if d3 >= 0 and d4 <= d3:
        return _corner(out, b, 1)
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        return _on_edge(out, a, ab0, ab1, ab2, d1 / (d1 - d3), 3)
    if d6 >= 0 and d5 <= d6:
        return _corner(out, c, 2)
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        return _on_edge(out, a, ac0, ac1, ac2, d2 / (d2 - d6), 5)
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        return _on_edge(out, b, c[0] - b[0], c[1] - b[1], c[2] - b[2],
                        (d4 - d3) / ((d4 - d3) + (d5 - d6)), 4)
    denom = va + vb + vc
    safe = denom if abs(denom) > 1e-300 else 1.0
    v = vb / safe
    w = vc / safe
    out[0] = a[0] + ab0 * v + ac0 * w
    out[1] = a[1] + ab1 * v + ac1 * w
    out[2] = a[2] + ab2 * v + ac2 * w
    return 6


@njit(cache=True, nogil=True, error_model="numpy")
def _norm3(x0: float, x1: float, x2: float) -> float:
    return np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


@njit(cache=True, nogil=True, error_model="numpy")
def build_grid(centroid: np.ndarray, cell: float):
    """Triangles binned by centroid on a uniform grid of cubes of side `cell` (m; widened so
    no axis has more than `MAX_CELLS` cells): (origin (3,), dims (3,), cell side,
    cell_start (cells+1,), cell_tri (m,), ascending triangle index within a cell)."""
    m = centroid.shape[0]
    lo = np.empty(3)
    hi = np.empty(3)
    dims = np.empty(3, dtype=np.int64)
    for a in range(3):
        mn, mx = np.inf, -np.inf
        for t in range(m):
            v = centroid[t, a]
            if v < mn:
                mn = v
            if v > mx:
                mx = v
        lo[a], hi[a] = mn, mx
        cell = max(cell, (mx - mn) / (MAX_CELLS - 1))
    for a in range(3):
        dims[a] = int((hi[a] - lo[a]) / cell) + 1
    n_cells = dims[0] * dims[1] * dims[2]
    cid = np.empty(m, dtype=np.int64)
    count = np.zeros(n_cells + 1, dtype=np.int64)
    for t in range(m):
        c = 0
        for a in range(3):
            k = int((centroid[t, a] - lo[a]) / cell)
            k = min(max(k, 0), dims[a] - 1)
            c = c * dims[a] + k
        cid[t] = c
        count[c + 1] += 1
    for c in range(n_cells):
        count[c + 1] += count[c]
    fill = count[:-1].copy()
    order = np.empty(m, dtype=np.int64)
    for t in range(m):
        order[fill[cid[t]]] = t
        fill[cid[t]] += 1
    return lo, dims, cell, count, order


@njit(cache=True, nogil=True, error_model="numpy")
def grid_nearest(p: np.ndarray, tri: np.ndarray, centroid: np.ndarray, radius: np.ndarray,
                 reach: float, plane: np.ndarray, offset: np.ndarray, slack: np.ndarray,
                 lo: np.ndarray, dims: np.ndarray, cell: float, cell_start: np.ndarray,
                 cell_tri: np.ndarray, dist: np.ndarray, point: np.ndarray, feat: np.ndarray,
                 which: np.ndarray) -> None:
    """Per point p[i] its closest triangle, exactly (`nearest_one`), into dist[i], point[i],
    feat[i] and which[i]."""
    q = np.empty(3)
    pc = np.empty(3, dtype=np.int64)
    for i in range(p.shape[0]):
        d, f, t = nearest_one(p[i], tri, centroid, radius, reach, plane, offset, slack, lo,
                              dims, cell, cell_start, cell_tri, point[i], q, pc)
        dist[i] = d
        feat[i] = f
        which[i] = t


@njit(cache=True, nogil=True, error_model="numpy")
def nearest_one(pi: np.ndarray, tri: np.ndarray, centroid: np.ndarray, radius: np.ndarray,
                reach: float, plane: np.ndarray, offset: np.ndarray, slack: np.ndarray,
                lo: np.ndarray, dims: np.ndarray, cell: float, cell_start: np.ndarray,
                cell_tri: np.ndarray, point: np.ndarray, q: np.ndarray, pc: np.ndarray):
    """The closest triangle to the point pi (3,), exactly: the least distance, the lowest
    triangle index among equal distances (the k-d tree scan's tie-break), a NaN distance as
    +inf. Returns (distance, feature, triangle) and writes the closest point into `point`
    (3,); `q` (3,) and `pc` (3,) int64 are scratch. Rings of grid cells are searched
    outward from the point's cell; a triangle is skipped only when a lower bound on its
    distance (centroid distance less its radius, or its plane's distance less its flatness
    slack) exceeds the best found, and the search stops once every unvisited cell's
    triangles lie farther (ring r+1 is ≥ r·cell away)."""
    for a in range(3):
        pc[a] = int(np.floor((pi[a] - lo[a]) / cell))
    # rings needed to cover the whole grid from here
    r_max = 0
    for a in range(3):
        r_max = max(r_max, abs(pc[a]), abs(dims[a] - 1 - pc[a]))
    best = np.inf
    best_t = -1
    best_f = 6
    b0 = b1 = b2 = 0.0
    for r in range(r_max + 1):
        if r >= 1 and (r - 1) * cell - reach > best + 1e-9:
            break
        x0, x1 = max(pc[0] - r, 0), min(pc[0] + r, dims[0] - 1)
        y0, y1 = max(pc[1] - r, 0), min(pc[1] + r, dims[1] - 1)
        z0, z1 = max(pc[2] - r, 0), min(pc[2] + r, dims[2] - 1)
        for x in range(x0, x1 + 1):
            ex = abs(x - pc[0]) == r
            for y in range(y0, y1 + 1):
                exy = ex or abs(y - pc[1]) == r
                if exy:
                    zs, zstep = z0, 1
                else:  # only the two faces z = pc ± r of this column are on the ring
                    zs, zstep = pc[2] - r, 2 * r
                z = zs
                while z <= z1:
                    if z >= z0:
                        c = (x * dims[1] + y) * dims[2] + z
                        for s in range(cell_start[c], cell_start[c + 1]):
                            t = cell_tri[s]
                            cd = _norm3(centroid[t, 0] - pi[0], centroid[t, 1] - pi[1],
                                        centroid[t, 2] - pi[2])
                            if cd - radius[t] > best + 1e-12:
                                continue
                            off = abs(_dot(plane[t, 0], plane[t, 1], plane[t, 2],
                                           pi[0], pi[1], pi[2]) - offset[t])
                            if off - slack[t] > best + 1e-9:
                                continue
                            f = closest_point(pi, tri[t, 0], tri[t, 1], tri[t, 2], q)
                            d = _norm3(q[0] - pi[0], q[1] - pi[1], q[2] - pi[2])
                            if d != d:
                                d = np.inf
                            if best_t < 0 or d < best or (d == best and t < best_t):
                                best, best_t, best_f = d, t, f
                                b0, b1, b2 = q[0], q[1], q[2]
                    if zstep == 0:
                        break
                    z += zstep
    point[0], point[1], point[2] = b0, b1, b2
    return best, best_f, best_t


@njit(cache=True, nogil=True, error_model="numpy")
def _separates(ax0: float, ax1: float, ax2: float, p: np.ndarray, q: np.ndarray) -> bool:
    """Whether the axis separates triangles p and q (3,3): their projections do not meet
    (touching counts as meeting)."""
    mn1 = mx1 = _dot(ax0, ax1, ax2, p[0, 0], p[0, 1], p[0, 2])
    for k in range(1, 3):
        s = _dot(ax0, ax1, ax2, p[k, 0], p[k, 1], p[k, 2])
        mn1, mx1 = min(mn1, s), max(mx1, s)
    mn2 = mx2 = _dot(ax0, ax1, ax2, q[0, 0], q[0, 1], q[0, 2])
    for k in range(1, 3):
        s = _dot(ax0, ax1, ax2, q[k, 0], q[k, 1], q[k, 2])
        mn2, mx2 = min(mn2, s), max(mx2, s)
    return mn1 > mx2 or mn2 > mx1


@njit(cache=True, nogil=True, error_model="numpy")
def triangles_meet(p: np.ndarray, q: np.ndarray) -> bool:
    """Separating-axis test of two triangles (3,3) (both normals, the 9 edge-edge cross products,
    and each normal crossed with its own edges for the coplanar case): True when no axis
    separates them, i.e. they intersect or touch."""
    e = np.empty((2, 3, 3))
    n = np.empty((2, 3))
    for s, t in ((0, p), (1, q)):
        for k in range(3):
            for a in range(3):
                e[s, k, a] = t[(k + 1) % 3, a] - t[k, a]
        n[s, 0] = e[s, 0, 1] * e[s, 1, 2] - e[s, 0, 2] * e[s, 1, 1]
        n[s, 1] = e[s, 0, 2] * e[s, 1, 0] - e[s, 0, 0] * e[s, 1, 2]
        n[s, 2] = e[s, 0, 0] * e[s, 1, 1] - e[s, 0, 1] * e[s, 1, 0]
    for s in range(2):
        if _separates(n[s, 0], n[s, 1], n[s, 2], p, q):
            return False
    for i in range(3):
        for j in range(3):
            a0 = e[0, i, 1] * e[1, j, 2] - e[0, i, 2] * e[1, j, 1]
            a1 = e[0, i, 2] * e[1, j, 0] - e[0, i, 0] * e[1, j, 2]
            a2 = e[0, i, 0] * e[1, j, 1] - e[0, i, 1] * e[1, j, 0]
            if _separates(a0, a1, a2, p, q):
                return False
    for s in range(2):
        for i in range(3):
            a0 = n[s, 1] * e[s, i, 2] - n[s, 2] * e[s, i, 1]
            a1 = n[s, 2] * e[s, i, 0] - n[s, 0] * e[s, i, 2]
            a2 = n[s, 0] * e[s, i, 1] - n[s, 1] * e[s, i, 0]
            if _separates(a0, a1, a2, p, q):
                return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def crossing_pairs(va: np.ndarray, fa: np.ndarray, vb: np.ndarray, fb: np.ndarray):
    """All pairs (i, j) of triangles fa[i] (corners in va) and fb[j] (in vb) that intersect or
    touch: their boxes overlap (a sweep along x over fa sorted by its boxes' low x), then
    `triangles_meet`. Returns (ia, ib), sorted by i then j."""
    na, nb = fa.shape[0], fb.shape[0]
    ta = np.empty((na, 3, 3))
    tb = np.empty((nb, 3, 3))
    for i in range(na):
        for k in range(3):
            for a in range(3):
                ta[i, k, a] = va[fa[i, k], a]
    for j in range(nb):
        for k in range(3):
            for a in range(3):
                tb[j, k, a] = vb[fb[j, k], a]
    lo_a = np.empty((na, 3))
    hi_a = np.empty((na, 3))
    lo_b = np.empty((nb, 3))
    hi_b = np.empty((nb, 3))
    for i in range(na):
        for a in range(3):
            lo_a[i, a] = min(ta[i, 0, a], ta[i, 1, a], ta[i, 2, a])
            hi_a[i, a] = max(ta[i, 0, a], ta[i, 1, a], ta[i, 2, a])
    for j in range(nb):
        for a in range(3):
            lo_b[j, a] = min(tb[j, 0, a], tb[j, 1, a], tb[j, 2, a])
            hi_b[j, a] = max(tb[j, 0, a], tb[j, 1, a], tb[j, 2, a])
    order = np.argsort(lo_a[:, 0], kind="mergesort")
    cap = 256
    ia = np.empty(cap, dtype=np.int64)
    ib = np.empty(cap, dtype=np.int64)
    n = 0
    for j in range(nb):
        for s in range(na):
            i = order[s]
            if lo_a[i, 0] > hi_b[j, 0]:
                break
            if (hi_a[i, 0] < lo_b[j, 0] or lo_a[i, 1] > hi_b[j, 1] or hi_a[i, 1] < lo_b[j, 1]
                    or lo_a[i, 2] > hi_b[j, 2] or hi_a[i, 2] < lo_b[j, 2]):
                continue
            if triangles_meet(ta[i], tb[j]):
                if n == cap:
                    cap *= 2
                    ia2 = np.empty(cap, dtype=np.int64)
                    ib2 = np.empty(cap, dtype=np.int64)
                    ia2[:n] = ia[:n]
                    ib2[:n] = ib[:n]
                    ia, ib = ia2, ib2
                ia[n] = i
                ib[n] = j
                n += 1
    key = np.argsort(ia[:n] * nb + ib[:n], kind="mergesort")
    return ia[:n][key], ib[:n][key]
