"""The mesh judge's per-frame work for solid components, compiled (numba), batch by batch.

Why: after the closest-triangle and crossing kernels (`closest`) were compiled, 60 % of the
judge's time was NumPy bookkeeping in Python per frame (face boxes, group filters, `np.unique`,
normals with `np.add.at`, the grid build, the flood's rounds). Here a batch of frames takes
three compiled calls and one NumPy call:

1. `broad_phase`: per frame the component boxes, the checked component pairs whose boxes meet,
   their faces in the overlap box, the group filters and the mutual box shrink, the centroid
   plane test, the crossing triangles (`closest.crossing_pairs`) and the checked crossings:
   flood jobs (frame, flooded component, solid it is tested against, seed vertices) and the
   (frame, solid) surfaces they need.
2. `corner_cosines`: each needed surface's triangle corner cosines, clipped to [-1, 1];
   NumPy's `np.arccos` turns them into angles (numba's `arccos` is libm's, which differs from
   NumPy's SIMD one in the last bit on some CPUs, and the vertex pseudo-normals must keep
   their bits).
3. `floods`: per surface its normals (face, edge, angle-weighted vertex), its triangle grid,
   then every flood job against it: the deepest inside vertex (`closest.nearest_one`).

Every floating-point step is the NumPy judge's (`depth.frame_depth_reference`) operation for
operation (products and sums in NumPy's order, NumPy's pairwise sum for a mean), so the depths
keep their bits; `tests/test_depth_exact.py` compares the two. The one exception is the
centroid plane test (`_separated`), a sound filter whose dot products NumPy hands to BLAS: it
can only differ on a pair whose two point sets touch within rounding, where no triangle pair
crosses anyway. Non-solid components (skins) stay in Python (`depth._skin_depth`).

numba's cache (`cache=True`) is keyed by the text of this file (a hash of its source): the
kernels it uses from `closest.py` are compiled into these, and an edit there alone leaves this
file's cached code stale. After editing `closest.py`, change this file's text too (a touch is not
enough), or clear `__pycache__`."""

from __future__ import annotations

import numpy as np
from numba import njit

from embody.collision.closest import build_grid, crossing_pairs, nearest_one


@njit(cache=True, nogil=True, error_model="numpy")
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """NumPy's pairwise sum of a block of at most 128: 8 accumulators, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    lim = n - n % 8
    while i < lim:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True, error_model="numpy")
def _pairwise_sum(a: np.ndarray) -> float:
    """NumPy's pairwise summation of a (1-D), so a mean has NumPy's bits: blocks of at most
    128 (`_block_sum`), halves split at a multiple of 8 and added left + right. NumPy's
    recursion, run on an explicit stack (numba's cache does not keep recursive functions
    safely)."""
    lo_s = np.empty(64, dtype=np.int64)
    n_s = np.empty(64, dtype=np.int64)
    state = np.empty(64, dtype=np.int64)
    vals = np.empty(64)
    lo_s[0], n_s[0], state[0] = 0, a.shape[0], 0
    top, nv = 1, 0
    while top > 0:
        lo, n = lo_s[top - 1], n_s[top - 1]
        if n <= 128:
            vals[nv] = _block_sum(a, lo, n)
            nv += 1
            top -= 1
            continue
        n2 = n // 2
        n2 -= n2 % 8
        if state[top - 1] == 0:
            state[top - 1] = 1
            lo_s[top], n_s[top], state[top] = lo, n2, 0
            top += 1
        elif state[top - 1] == 1:
            state[top - 1] = 2
            lo_s[top], n_s[top], state[top] = lo + n2, n - n2, 0
            top += 1
        else:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            top -= 1
    return vals[0]


@njit(cache=True, nogil=True, error_model="numpy")
def _nanmax(a: float, b: float) -> float:
    """np.maximum: NaN wins."""
    if a != a or b != b:
        return a + b
    return a if a >= b else b


@njit(cache=True, nogil=True, error_model="numpy")
def _floor(x: float, lo: float) -> float:
    """np.maximum(x, lo) for a positive floor: NaN stays NaN."""
    return lo if x < lo else x


@njit(cache=True, nogil=True, error_model="numpy")
def _face_boxes(vt: np.ndarray, gfaces: np.ndarray, f0: int, f1: int, fmin: np.ndarray,
                fmax: np.ndarray) -> None:
    for f in range(f0, f1):
        a, b, c = gfaces[f, 0], gfaces[f, 1], gfaces[f, 2]
        for k in range(3):
            fmin[f, k] = min(min(vt[a, k], vt[b, k]), vt[c, k])
            fmax[f, k] = max(max(vt[a, k], vt[b, k]), vt[c, k])


@njit(cache=True, nogil=True, error_model="numpy")
def _in_box(fmin: np.ndarray, fmax: np.ndarray, f: int, lo: np.ndarray, hi: np.ndarray) -> bool:
    return (fmax[f, 0] >= lo[0] and fmax[f, 1] >= lo[1] and fmax[f, 2] >= lo[2]
            and fmin[f, 0] <= hi[0] and fmin[f, 1] <= hi[1] and fmin[f, 2] <= hi[2])


@njit(cache=True, nogil=True, error_model="numpy")
def _faces_in_box(fmin: np.ndarray, fmax: np.ndarray, f0: int, f1: int, lo: np.ndarray,
                  hi: np.ndarray, out: np.ndarray) -> int:
    """The faces f0..f1-1 whose boxes meet the box lo..hi, into out; returns their count."""
    l0, l1, l2, h0, h1, h2 = lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
    n = 0
    for f in range(f0, f1):
        if (fmax[f, 0] >= l0 and fmax[f, 1] >= l1 and fmax[f, 2] >= l2
                and fmin[f, 0] <= h0 and fmin[f, 1] <= h1 and fmin[f, 2] <= h2):
            out[n] = f
            n += 1
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def _group_filter(s: np.ndarray, n: int, other: np.ndarray, m: int, fgroup: np.ndarray,
                  checked: np.ndarray, present: np.ndarray, keep: np.ndarray) -> int:
    """Keep (in place, in order) the faces s[:n] whose group is checked against the group of
    some face other[:m]; returns the count kept. Which groups pass is settled once per call
    (`keep`, G×G), not once per face (up to G tests a face; the same faces kept)."""
    present[:] = False
    for k in range(m):
        present[fgroup[other[k]]] = True
    for g in range(present.shape[0]):
        keep[g] = False
        for h in range(present.shape[0]):
            if present[h] and checked[g, h]:
                keep[g] = True
                break
    kept = 0
    for k in range(n):
        if keep[fgroup[s[k]]]:
            s[kept] = s[k]
            kept += 1
    return kept


@njit(cache=True, nogil=True, error_model="numpy")
def _within(s: np.ndarray, n: int, other: np.ndarray, m: int, fmin: np.ndarray,
            fmax: np.ndarray) -> int:
    """Keep (in place) the faces s[:n] whose boxes meet the box of the faces other[:m]."""
    if n == 0 or m == 0:
        return 0
    lo = fmin[other[0]].copy()
    hi = fmax[other[0]].copy()
    for k in range(1, m):
        for a in range(3):
            lo[a] = min(lo[a], fmin[other[k], a])
            hi[a] = max(hi[a], fmax[other[k], a])
    kept = 0
    for k in range(n):
        if _in_box(fmin, fmax, s[k], lo, hi):
            s[kept] = s[k]
            kept += 1
    return kept


@njit(cache=True, nogil=True, error_model="numpy")
def _mark_vertices(s: np.ndarray, n: int, faces: np.ndarray, v0: int, mark: np.ndarray,
                   stamp: int) -> None:
    """mark[v0 + local vertex] = stamp for every corner of the faces s[:n]."""
    for k in range(n):
        for c in range(3):
            mark[v0 + faces[s[k], c]] = stamp


@njit(cache=True, nogil=True, error_model="numpy")
def _mean_marked(vt: np.ndarray, verts: np.ndarray, v0: int, v1: int, mark: np.ndarray,
                 stamp: int) -> np.ndarray:
    """Mean of the marked vertices in ascending id order (NumPy's axis-0 mean: rows summed in
    turn, then divided by the count)."""
    s = np.zeros(3)
    n = 0
    for u in range(v0, v1):
        if mark[u] == stamp:
            g = verts[u]
            if n == 0:
                s[0], s[1], s[2] = vt[g, 0], vt[g, 1], vt[g, 2]
            else:
                s[0] += vt[g, 0]
                s[1] += vt[g, 1]
                s[2] += vt[g, 2]
            n += 1
    return s / n


@njit(cache=True, nogil=True, error_model="numpy")
def _projection(vt: np.ndarray, verts: np.ndarray, v0: int, v1: int, mark: np.ndarray,
                stamp: int, axis: np.ndarray, want_max: bool) -> float:
    out = -np.inf if want_max else np.inf
    for u in range(v0, v1):
        if mark[u] == stamp:
            g = verts[u]
            x = (vt[g, 0] * axis[0] + vt[g, 1] * axis[1]) + vt[g, 2] * axis[2]
            out = max(out, x) if want_max else min(out, x)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _slots_meet(sbox: np.ndarray, slot_group: np.ndarray, checked: np.ndarray, a0: int,
                a1: int, b0: int, b1: int) -> bool:
    """Whether a slot of a0..a1-1 and one of b0..b1-1 are a checked pair of groups whose
    boxes meet (inclusive, as `crossing_pairs`)."""
    for qa in range(a0, a1):
        for qb in range(b0, b1):
            if not checked[slot_group[qa], slot_group[qb]]:
                continue
            if (sbox[qa, 0, 0] <= sbox[qb, 1, 0] and sbox[qb, 0, 0] <= sbox[qa, 1, 0]
                    and sbox[qa, 0, 1] <= sbox[qb, 1, 1] and sbox[qb, 0, 1] <= sbox[qa, 1, 1]
                    and sbox[qa, 0, 2] <= sbox[qb, 1, 2] and sbox[qb, 0, 2] <= sbox[qa, 1, 2]):
                return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def broad_phase(vertices: np.ndarray, vptr: np.ndarray, verts: np.ndarray, fptr: np.ndarray,
                faces: np.ndarray, gfaces: np.ndarray, fgroup: np.ndarray, solid: np.ndarray,
                checked: np.ndarray, pairs: np.ndarray, slot_ptr: np.ndarray,
                slot_group: np.ndarray, slot_vptr: np.ndarray, slot_verts: np.ndarray):
    """Flood jobs and the surfaces they need, for frames `vertices` (T,V,3).

    A pair of components whose boxes meet goes on only if the boxes of two of their face
    groups that are a checked pair meet (`slot_*`: per component its face groups' vertices;
    the union of a component's slot boxes is its box): a checked crossing needs two faces of
    such groups whose boxes meet (`crossing_pairs` sweeps the same inclusive boxes), each box
    inside its group's, so a pair this skips has no checked crossing and gave no job.

    Returns (job_frame, job_flooded, job_surface, seed_ptr, seeds (component-local vertex
    ids), surface_frame, surface_component); a job floods component `job_flooded` of its
    frame against surface `job_surface` (a solid of the same frame)."""
    n_frames = vertices.shape[0]
    n_comp = vptr.shape[0] - 1
    n_groups = checked.shape[0]
    n_faces = faces.shape[0]
    fmin = np.empty((n_faces, 3))
    fmax = np.empty((n_faces, 3))
    boxed = np.zeros(n_comp, dtype=np.int64)       # frame + 1 whose face boxes are in fmin/fmax
    surface = np.full(n_comp, -1, dtype=np.int64)
    box = np.empty((n_comp, 2, 3))
    most = 0
    for c in range(n_comp):
        most = max(most, fptr[c + 1] - fptr[c])
    si = np.empty(most, dtype=np.int64)
    sj = np.empty(most, dtype=np.int64)
    present = np.zeros(n_groups, dtype=np.bool_)
    keep = np.zeros(n_groups, dtype=np.bool_)
    mark = np.zeros(verts.shape[0], dtype=np.int64)
    stamp = 0
    lo = np.empty(3)
    hi = np.empty(3)
    job_frame, job_flooded, job_surface, seed_ptr, seeds = [0], [0], [0], [0], [0]
    job_frame.pop()
    job_flooded.pop()
    job_surface.pop()
    seeds.pop()
    surf_frame, surf_comp = [0], [0]
    surf_frame.pop()
    surf_comp.pop()
    sbox = np.empty((slot_group.shape[0], 2, 3))
    for t in range(n_frames):
        vt = vertices[t]
        for q in range(slot_group.shape[0]):
            g = slot_verts[slot_vptr[q]]
            for a in range(3):
                sbox[q, 0, a] = vt[g, a]
                sbox[q, 1, a] = vt[g, a]
            for u in range(slot_vptr[q] + 1, slot_vptr[q + 1]):
                g = slot_verts[u]
                for a in range(3):
                    x = vt[g, a]
                    if x < sbox[q, 0, a]:
                        sbox[q, 0, a] = x
                    if x > sbox[q, 1, a]:
                        sbox[q, 1, a] = x
        for c in range(n_comp):
            for a in range(3):
                box[c, 0, a] = sbox[slot_ptr[c], 0, a]
                box[c, 1, a] = sbox[slot_ptr[c], 1, a]
            for q in range(slot_ptr[c] + 1, slot_ptr[c + 1]):
                for a in range(3):
                    box[c, 0, a] = min(box[c, 0, a], sbox[q, 0, a])
                    box[c, 1, a] = max(box[c, 1, a], sbox[q, 1, a])
            surface[c] = -1
        for p in range(pairs.shape[0]):
            i, j = pairs[p, 0], pairs[p, 1]
            apart = False
            for a in range(3):
                lo[a] = max(box[i, 0, a], box[j, 0, a])
                hi[a] = min(box[i, 1, a], box[j, 1, a])
                if lo[a] > hi[a]:
                    apart = True
            if apart or not _slots_meet(sbox, slot_group, checked, slot_ptr[i],
                                        slot_ptr[i + 1], slot_ptr[j], slot_ptr[j + 1]):
                continue
            for c in (i, j):
                if boxed[c] != t + 1:
                    _face_boxes(vt, gfaces, fptr[c], fptr[c + 1], fmin, fmax)
                    boxed[c] = t + 1
            ni = _faces_in_box(fmin, fmax, fptr[i], fptr[i + 1], lo, hi, si)
            nj = _faces_in_box(fmin, fmax, fptr[j], fptr[j + 1], lo, hi, sj)
            ni = _group_filter(si, ni, sj, nj, fgroup, checked, present, keep)
            nj = _group_filter(sj, nj, si, ni, fgroup, checked, present, keep)
            ni = _within(si, ni, sj, nj, fmin, fmax)
            nj = _within(sj, nj, si, ni, fmin, fmax)
            if ni == 0 or nj == 0:
                continue
            # the centroid plane test (`depth._separated`)
            stamp += 1
            _mark_vertices(si, ni, faces, vptr[i], mark, stamp)
            _mark_vertices(sj, nj, faces, vptr[j], mark, stamp)
            ma = _mean_marked(vt, verts, vptr[i], vptr[i + 1], mark, stamp)
            mb = _mean_marked(vt, verts, vptr[j], vptr[j + 1], mark, stamp)
            axis = mb - ma
            if (_projection(vt, verts, vptr[i], vptr[i + 1], mark, stamp, axis, True)
                    < _projection(vt, verts, vptr[j], vptr[j + 1], mark, stamp, axis, False)):
                continue
            xi, xj = crossing_pairs(vt, gfaces[si[:ni]], vt, gfaces[sj[:nj]])
            kept = 0
            for k in range(xi.shape[0]):
                if checked[fgroup[si[xi[k]]], fgroup[sj[xj[k]]]]:
                    xi[kept] = xi[k]
                    xj[kept] = xj[k]
                    kept += 1
            if kept == 0:  # crossing only where contact is expected (e.g. at a joint)
                continue
            for side in range(2):
                a, b = (i, j) if side == 0 else (j, i)
                if not solid[b]:
                    continue
                if surface[b] < 0:
                    surface[b] = len(surf_frame)
                    surf_frame.append(t)
                    surf_comp.append(b)
                stamp += 1
                x = xi if side == 0 else xj
                s = si if side == 0 else sj
                for k in range(kept):
                    for c in range(3):
                        u = vptr[a] + faces[s[x[k]], c]
                        if mark[u] != stamp:
                            mark[u] = stamp
                            seeds.append(faces[s[x[k]], c])
                job_frame.append(t)
                job_flooded.append(a)
                job_surface.append(surface[b])
                seed_ptr.append(len(seeds))
    return (_array(job_frame), _array(job_flooded), _array(job_surface), _array(seed_ptr),
            _array(seeds), _array(surf_frame), _array(surf_comp))


@njit(cache=True, nogil=True, error_model="numpy")
def _array(values) -> np.ndarray:
    out = np.empty(len(values), dtype=np.int64)
    for k in range(len(values)):
        out[k] = values[k]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _norm(x0: float, x1: float, x2: float) -> float:
    return np.sqrt((x0 * x0 + x1 * x1) + x2 * x2)


@njit(cache=True, nogil=True, error_model="numpy")
def _corner(tri: np.ndarray, f: int, k: int) -> float:
    """Cosine of triangle f's corner k (NumPy judge's `_normals` form), clipped to [-1, 1]."""
    k1, k2 = (k + 1) % 3, (k + 2) % 3
    e10 = tri[f, k1, 0] - tri[f, k, 0]
    e11 = tri[f, k1, 1] - tri[f, k, 1]
    e12 = tri[f, k1, 2] - tri[f, k, 2]
    e20 = tri[f, k2, 0] - tri[f, k, 0]
    e21 = tri[f, k2, 1] - tri[f, k, 1]
    e22 = tri[f, k2, 2] - tri[f, k, 2]
    cos = (e10 * e20 + e11 * e21) + e12 * e22
    cos = cos / _floor(_norm(e10, e11, e12) * _norm(e20, e21, e22), 1e-300)
    if cos < -1.0:
        return -1.0
    if cos > 1.0:
        return 1.0
    return cos


@njit(cache=True, nogil=True, error_model="numpy")
def _triangles(vt: np.ndarray, gfaces: np.ndarray, f0: int, f1: int) -> np.ndarray:
    tri = np.empty((f1 - f0, 3, 3))
    for f in range(f0, f1):
        for k in range(3):
            for a in range(3):
                tri[f - f0, k, a] = vt[gfaces[f, k], a]
    return tri


@njit(cache=True, nogil=True, error_model="numpy")
def corner_cosines(vertices: np.ndarray, fptr: np.ndarray, gfaces: np.ndarray,
                   surf_frame: np.ndarray, surf_comp: np.ndarray):
    """(cosines, offsets): per surface its triangles' corner cosines, corner 0 of every
    triangle, then corner 1, then corner 2 (the order `np.add.at` sums them in)."""
    ptr = np.zeros(surf_frame.shape[0] + 1, dtype=np.int64)
    for s in range(surf_frame.shape[0]):
        c = surf_comp[s]
        ptr[s + 1] = ptr[s] + 3 * (fptr[c + 1] - fptr[c])
    out = np.empty(ptr[-1])
    for s in range(surf_frame.shape[0]):
        c = surf_comp[s]
        tri = _triangles(vertices[surf_frame[s]], gfaces, fptr[c], fptr[c + 1])
        m = tri.shape[0]
        for k in range(3):
            for f in range(m):
                out[ptr[s] + k * m + f] = _corner(tri, f, k)
    return out, ptr


#: `floods` skips the closest-triangle query of a vertex whose lower bound on its depth exceeds
#: this (m: it is inside, with a margin far above rounding) and whose upper bound is below the
#: deepest depth found by this margin (m): the query could neither stop the flood there nor
#: raise the frame's depth, so the depths keep their bits.
_INSIDE_BY = 1e-6
_BOUND_SLACK = 1e-9


@njit(cache=True, nogil=True, error_model="numpy")
def floods(vertices: np.ndarray, vptr: np.ndarray, verts: np.ndarray, vgroup: np.ndarray,
           fptr: np.ndarray, faces: np.ndarray, gfaces: np.ndarray, fgroup: np.ndarray,
           eof: np.ndarray, eptr: np.ndarray, efaces: np.ndarray, nptr: np.ndarray,
           nidx: np.ndarray, checked: np.ndarray, allowed: np.ndarray,
           surf_frame: np.ndarray, surf_comp: np.ndarray, angles: np.ndarray,
           angle_ptr: np.ndarray, job_frame: np.ndarray, job_flooded: np.ndarray,
           job_surface: np.ndarray, seed_ptr: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Per frame the deepest vertex found by the flood jobs (0 without one)."""
    best = np.zeros(vertices.shape[0])
    n_surf = surf_frame.shape[0]
    # jobs by surface
    count = np.zeros(n_surf + 1, dtype=np.int64)
    for k in range(job_surface.shape[0]):
        count[job_surface[k] + 1] += 1
    for s in range(n_surf):
        count[s + 1] += count[s]
    fill = count[:-1].copy()
    order = np.empty(job_surface.shape[0], dtype=np.int64)
    for k in range(job_surface.shape[0]):
        order[fill[job_surface[k]]] = k
        fill[job_surface[k]] += 1
    q = np.empty(3)
    scratch = np.empty(3)
    pc = np.empty(3, dtype=np.int64)
    for s in range(n_surf):
        t, b = surf_frame[s], surf_comp[s]
        vt = vertices[t]
        f0, f1 = fptr[b], fptr[b + 1]
        m = f1 - f0
        tri = _triangles(vt, gfaces, f0, f1)
        # face normals
        fn = np.empty((m, 3))
        for f in range(m):
            a0 = tri[f, 1, 0] - tri[f, 0, 0]
            a1 = tri[f, 1, 1] - tri[f, 0, 1]
            a2 = tri[f, 1, 2] - tri[f, 0, 2]
            c0 = tri[f, 2, 0] - tri[f, 0, 0]
            c1 = tri[f, 2, 1] - tri[f, 0, 1]
            c2 = tri[f, 2, 2] - tri[f, 0, 2]
            n0 = a1 * c2 - a2 * c1
            n1 = a2 * c0 - a0 * c2
            n2 = a0 * c1 - a1 * c0
            d = _floor(_norm(n0, n1, n2), 1e-300)
            fn[f, 0], fn[f, 1], fn[f, 2] = n0 / d, n1 / d, n2 / d
        # edge pseudo-normals
        e0, e1 = eptr[b], eptr[b + 1]
        en = np.empty((e1 - e0, 3))
        for e in range(e0, e1):
            g0, g1 = efaces[e, 0], efaces[e, 1]
            for a in range(3):
                en[e - e0, a] = fn[g0, a] + (fn[g1, a] if g1 >= 0 else 0.0)
        # angle-weighted vertex normals, summed as np.add.at does (corner 0 of every face,
        # then corner 1, then corner 2)
        v0, v1 = vptr[b], vptr[b + 1]
        vn = np.zeros((v1 - v0, 3))
        for k in range(3):
            for f in range(m):
                w = angles[angle_ptr[s] + k * m + f]
                u = faces[f0 + f, k]
                for a in range(3):
                    vn[u, a] = vn[u, a] + w * fn[f, a]
        # the closest-triangle grid (`depth._Surface`)
        centroid = np.empty((m, 3))
        radius = np.empty(m)
        offset = np.empty(m)
        slack = np.empty(m)
        for f in range(m):
            for a in range(3):
                centroid[f, a] = ((tri[f, 0, a] + tri[f, 1, a]) + tri[f, 2, a]) / 3.0
            r = _norm(tri[f, 0, 0] - centroid[f, 0], tri[f, 0, 1] - centroid[f, 1],
                      tri[f, 0, 2] - centroid[f, 2])
            for k in range(1, 3):
                r = _nanmax(r, _norm(tri[f, k, 0] - centroid[f, 0],
                                     tri[f, k, 1] - centroid[f, 1],
                                     tri[f, k, 2] - centroid[f, 2]))
            radius[f] = r
            o = (fn[f, 0] * tri[f, 0, 0] + fn[f, 1] * tri[f, 0, 1]) + fn[f, 2] * tri[f, 0, 2]
            offset[f] = o
            s1 = (fn[f, 0] * tri[f, 1, 0] + fn[f, 1] * tri[f, 1, 1]) + fn[f, 2] * tri[f, 1, 2]
            s2 = (fn[f, 0] * tri[f, 2, 0] + fn[f, 1] * tri[f, 2, 1]) + fn[f, 2] * tri[f, 2, 2]
            slack[f] = _nanmax(abs(s1 - o), abs(s2 - o))
        reach = radius[0]
        for f in range(1, m):
            reach = _nanmax(reach, radius[f])
        cell = 2.0 * (_pairwise_sum(radius) / m)
        if 1e-6 > cell:  # Python's max(cell, 1e-6): NaN stays
            cell = 1e-6
        lo, dims, cell, start, cell_tri = build_grid(centroid, cell)
        for k in range(count[s], count[s + 1]):
            job = order[k]
            a = job_flooded[job]
            w0, w1 = vptr[a], vptr[a + 1]
            seen = np.zeros(w1 - w0, dtype=np.bool_)
            for u in range(w1 - w0):
                seen[u] = not allowed[b, vgroup[w0 + u]]
            stack = np.empty(w1 - w0, dtype=np.int64)
            # bounds on a vertex's distance to the surface, from its visited neighbours (their
            # distance, or their bounds, ± the edge between them; the tightest): NaN until one
            low = np.full(w1 - w0, np.nan)
            high = np.full(w1 - w0, np.nan)
            popped = np.zeros(w1 - w0, dtype=np.bool_)
            top = 0
            for k2 in range(seed_ptr[job], seed_ptr[job + 1]):
                u = seeds[k2]
                if not seen[u]:
                    seen[u] = True
                    stack[top] = u
                    top += 1
            deepest = 0.0
            while top > 0:
                top -= 1
                u = stack[top]
                p = vt[verts[w0 + u]]
                lo_u, hi_u = low[u], high[u]
                if lo_u > _INSIDE_BY and hi_u < max(deepest, best[t]) - _BOUND_SLACK:
                    # inside (the ball of radius lo_u around its pusher holds no surface) and
                    # no deeper than a depth already found: the query could change nothing
                    d = np.nan
                else:
                    d, feat, face = nearest_one(p, tri, centroid, radius, reach, fn, offset,
                                                slack, lo, dims, cell, start, cell_tri, q,
                                                scratch, pc)
                    if feat < 3:
                        nrm = vn[faces[f0 + face, feat]]
                    elif feat < 6:
                        nrm = en[eof[f0 + face, feat - 3]]
                    else:
                        nrm = fn[face]
                    side = (((p[0] - q[0]) * nrm[0] + (p[1] - q[1]) * nrm[1])
                            + (p[2] - q[2]) * nrm[2])
                    if not side < 0:
                        continue
                    if checked[vgroup[w0 + u], fgroup[f0 + face]] and d > deepest:
                        deepest = d
                    lo_u, hi_u = d, d
                popped[u] = True
                for k3 in range(nptr[w0 + a + u], nptr[w0 + a + u + 1]):
                    nb = nidx[k3]
                    if popped[nb]:
                        continue
                    # a neighbour still to visit: pushed now, or its bounds narrowed
                    r = vt[verts[w0 + nb]]
                    e = _norm(r[0] - p[0], r[1] - p[1], r[2] - p[2])
                    if not low[nb] >= lo_u - e:
                        low[nb] = lo_u - e
                    if not high[nb] <= hi_u + e:
                        high[nb] = hi_u + e
                    if not seen[nb]:
                        seen[nb] = True
                        stack[top] = nb
                        top += 1
            if deepest > best[t]:
                best[t] = deepest
    return best
