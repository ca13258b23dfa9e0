"""IK residual keeping the robot's hands apart (from each other, from the chest and from the face)
where the human's are apart, at hand scale.

Why: the shape fit maps wrist positions with the arm-span ratio (G1: 0.76 of the human), but a
Dex3 hand is as long as 1.4 human hands (wrist → middle tip). Two human hands 3-5 cm apart become
two robot hands that would overlap, so the self-collision term parks them at its margin: the
robot "touches" wherever the human's hands merely pass near each other (Table III: ~17 robot
contact events per sequence against the human's 3.5, hand-hand precision 0.2-0.4).

The gap between the hands is a property of the hands, so it is scaled by the hand-size ratio ρ
(robot hand length / human hand length): where the human's hands are apart (mesh gap g > the
human contact ε), the robot's hand-hand clearance must be at least min(ρ·g, `ik.hand_gap_max`),
a one-sided hinge √w·relu(g* − d(q)) on the closest pair; d is the proxies' clearance (surface
points of one hand against the polytopes of the other's geoms, both ways: the same geometry the
collision term uses, an underestimate near polytope edges, so the hands stay at least that far).
Where the human's hands touch, g* = 0 and the term is silent: the collision term's margin makes
the touch a touch without penetration. The same holds between each hand and the chest (the torso
hulls at the sternum and belly landmarks): a G1 torso is thin and its arms short, so a human hand
3-5 cm before the chest otherwise rests on the robot's; and between each hand and the face (the
head hulls at the face landmarks): a hand passing 2-3 cm from the human's face (the opposite-
shoulder sign, the chin signs' approach) otherwise brushes the robot's. The fidelity measure judges robot contacts at the same
hand scale (ε·ρ, `embody.metrics.fidelity`), so a gap the human calls a contact maps to one the
robot's measure calls a contact, and a gap it does not call one maps to one it does not.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
from numba import njit

from embody.clusters import median_cuts
from embody.metrics.fidelity import hand_length, hand_ratio  # noqa: F401  (re-exported: one definition)
from embody.retarget.jacobians import normal_jacobian
from embody.retarget.proxy_hulls import max_planes, plane_table
from embody.robot import Robot
from embody.robot.fk import rotate
from embody.robot.contacts import subtree_ids
from embody.robot.proxies import robot_proxies

SIDES = ("left", "right")
#: Gap columns of `Targets.hand_gap`: the human contact channels they come from.
CHANNELS = ("hands", "left_chest", "right_chest", "left_face", "right_face")
#: Chest (face) hulls: hulls of the landmark's body within this (m) of the sternum or belly
#: (a face) landmark.
_CHEST_REACH = 0.03
_FACE = ("forehead", "nose", "mouth", "chin", "left_cheek", "right_cheek")


class HandClearanceTerm:
    """Hinge rows √(w·scale)·relu(gap_c(t) − d_h(q)), one per hull h of a channel c (d_h: the
    closest proxy point of the hand facing it), for frames with gap_c > 0. Channels: hands
    (left points vs right hulls and back), each hand vs the chest hulls."""

    #: each (frame, hull)'s closest hand point in one compiled pass (`_closest`); False: the
    #: NumPy form below it (the reference the tests hold the kernel to)
    compiled: bool = True
    #: in the NumPy form, the points' largest plane distance over their hulls: None = the
    #: compiled pass (`proxy_hulls.max_planes`); the tests set `proxy_hulls.max_planes_numpy`
    planes: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None

    def __init__(self, robot: Robot, gap: np.ndarray, w: float) -> None:
        self.gap = np.asarray(gap, dtype=np.float64).reshape(len(gap), -1)
        self.w = float(w)
        # the tables below depend on the robot (and the gap's channel count) only: built once per
        # robot, not per solve (~60 ms each; the IK builds a term per LM problem, several per solve)
        key = ("hand_clearance", self.gap.shape[1])
        if key not in robot.derived:
            robot.derived[key] = self._tables(robot, self.gap.shape[1])
        self.__dict__.update(robot.derived[key])

    @staticmethod
    def _tables(robot: Robot, channels: int) -> dict[str, object]:
        """The term's robot tables (attributes): pairs, bodies, width, bound planes, rows, hands."""
        tables = SimpleNamespace()
        px = robot_proxies(robot)
        m = robot.model
        hand: dict[str, set[str]] = {}
        for s in SIDES:
            sub = subtree_ids(m, robot.spec.landmarks[f"{s}_wrist"].body)
            hand[s] = {m.body(b).name for b in sub}
        in_hand = lambda names, s: np.array([px.bodies[b] in hand[s] for b in names], dtype=bool)  # noqa: E731
        points = {s: np.flatnonzero(in_hand(px.sphere_body, s)) for s in SIDES}
        hulls = {s: np.flatnonzero(in_hand(px.hull_body, s)) for s in SIDES}
        def near(names: tuple[str, ...]) -> np.ndarray:
            lms = [robot.spec.landmarks[n] for n in names if n in robot.spec.landmarks]
            out = []
            for h in range(len(px.hull_body)):
                for lm in lms:
                    if px.bodies[px.hull_body[h]] == lm.body:
                        planes = px.hull_planes[h]
                        if (planes[:, :3] @ np.asarray(lm.offset) + planes[:, 3]).max() < _CHEST_REACH:
                            out.append(h)
                            break
            return np.array(out, dtype=np.int64)

        chest, face = near(("sternum", "belly")), near(_FACE)
        #: (gap column, proxy points, hulls) per direction
        tables.pairs = [(0, points["left"], hulls["right"]), (0, points["right"], hulls["left"]),
                      (1, points["left"], chest), (2, points["right"], chest),
                      (3, points["left"], face), (4, points["right"], face)]
        tables.pairs = [(c, p, h) for c, p, h in tables.pairs if c < channels and len(p) and len(h)]
        tables.px = px
        used = {px.bodies[b] for _, p, h in tables.pairs for b in np.r_[px.sphere_body[p]]}
        used |= {px.bodies[b] for _, p, h in tables.pairs for b in px.hull_body[h]}
        #: bodies the FK must walk (the costs add them to their body set)
        tables.bodies = sorted(used)
        #: one row per (pair, hull)
        tables.width = sum(len(h) for _, _, h in tables.pairs)
        #: per hull, a few planes of well-spread normals: their max is a lower bound of the
        #: hull's max-plane value (every plane is), so points it puts at ≥ the gap are culled exactly
        tables.bound_planes = {h: px.hull_planes[h][_spread(px.hull_planes[h][:, :3], _BOUND_PLANES)]
                               for _, _, hulls in tables.pairs for h in hulls}
        #: per pair: its bound planes stacked (H,K,4) (short sets padded by repeating their first
        #: plane, which changes no max), its hulls' plane sets without the padding, its first row
        pad = lambda p: np.vstack([p, np.repeat(p[:1], _BOUND_PLANES - len(p), 0)])  # noqa: E731
        tables.pair_bounds = [np.stack([pad(tables.bound_planes[h]) for h in hulls]) for _, _, hulls in tables.pairs]
        tables.pair_bounds_t = [np.ascontiguousarray(np.swapaxes(b[..., :3], -1, -2)) for b in tables.pair_bounds]
        tables.exact_planes = [[_unpadded(px.hull_planes[h]) for h in hulls] for _, _, hulls in tables.pairs]
        #: the same per pair as one zero-padded table and its counts (`proxy_hulls.max_planes`)
        tables.plane_tables = [plane_table(planes) for planes in tables.exact_planes]
        tables.row0 = np.cumsum([0] + [len(h) for _, _, h in tables.pairs])[:-1]
        #: per hand (keyed by its point array): its points in clusters on one body, each one's ball
        tables.hands = {id(p): _hand_table(px, p) for _, p, _ in tables.pairs}
        return vars(tables)

    def _hand(self, pose, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (T,P,3) of a hand's proxy points, the centres of its clusters' balls (T,nc,3)
        and the points' FK columns: cluster by cluster (one 3×3 @ 3×m product each, per frame)."""
        px, tab = self.px, self.hands[id(pts)]
        bcol = np.array([pose.index[px.bodies[b]] for b in tab["body"]])
        rot, pos = pose.rot[:, bcol], pose.pos[:, bcol]
        xb = np.swapaxes(rot @ tab["local"] + pos[..., None], -1, -2)  # (T,nb,m,3)
        x = np.empty((len(rot), len(pts), 3))
        x[:, tab["table"][tab["valid"]]] = xb[:, tab["valid"]]
        centre = rotate(rot, tab["centre"]) + pos
        return x, centre, bcol[tab["slot"]]

    def rows(self, pose, scale: float) -> tuple[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """The IK's `ResidualTerm` protocol (`costs.py`); phased in with the collision term
        (`scale`), since both keep parts apart.

        Exact culling, coarse to fine, each level a lower bound of a point's max-plane value
        (a few of the hull's planes, `bound_planes`, taken to the world once per frame):
        a cluster's ball (≤ `_CLUSTER` points of one body; centre value − radius) drops all its
        points for a hull, then each remaining point's own bound drops it; only points whose bound
        is below the gap get the full plane set. All hulls of a pair go in one batch. Rows equal the
        brute force (tests/test_hand_clearance.py)."""
        sw = np.sqrt(max(self.w * float(scale), 0.0))
        if sw == 0.0 or not self.pairs:
            return None
        t, px = len(pose.rot), self.px
        r = np.zeros((t, self.width))
        act_f, act_row, act_x, act_n, act_pb, act_hb = [], [], [], [], [], []
        hands: dict[int, tuple] = {}
        for k, (c, pts, hulls) in enumerate(self.pairs):
            frames = np.flatnonzero(self.gap[:, c] > 0)
            if not len(frames):
                continue
            if id(pts) not in hands:
                hands[id(pts)] = self._hand(pose, pts)
            x, centre, pcol = hands[id(pts)]
            tab, gap, row0 = self.hands[id(pts)], self.gap[frames, c], self.row0[k]
            hcol = np.array([pose.index[px.bodies[px.hull_body[h]]] for h in hulls])
            r_h, p_h = pose.rot[frames[:, None], hcol], pose.pos[frames[:, None], hcol]  # (F,H,..)
            if self.compiled:
                value, point, normal_l = _closest(
                    frames, gap, x, centre, tab["radius"], tab["table"], px.radii[pts],
                    np.ascontiguousarray(pose.rot), np.ascontiguousarray(pose.pos), hcol,
                    self.pair_bounds[k], *self.plane_tables[k])
                r[frames, row0:row0 + len(hulls)] = sw * np.maximum(gap[:, None] - value, 0.0)
                fa, ha = np.nonzero(value < gap[:, None])
                if len(fa):
                    act_f.append(frames[fa])
                    act_row.append(row0 + ha)
                    act_x.append(x[frames[fa], point[fa, ha]])
                    act_n.append(np.einsum("fab,fb->fa", r_h[fa, ha], normal_l[fa, ha]))
                    act_pb.append(pcol[point[fa, ha]])
                    act_hb.append(hcol[ha])
                continue
            bound = self.pair_bounds[k]  # (H,K,4)
            n_wt = r_h @ self.pair_bounds_t[k]  # (F,H,3,K): the normals in the world
            d_w = bound[..., 3] - (p_h[:, :, None] @ n_wt)[:, :, 0]  # (F,H,K)
            # a cluster's ball: n·x + d ≥ n·c + d − radius for every point x in it
            lb = (centre[frames][:, None] @ n_wt + d_w[:, :, None]).max(-1) - tab["radius"]  # (F,H,nc)
            fi, hi, bi = np.nonzero(lb < gap[:, None, None])
            if not len(fi):
                continue
            tbl = tab["table"][bi]  # (N,m)
            lbp = (x[frames[fi][:, None], tbl] @ n_wt[fi, hi] + d_w[fi, hi][:, None]).max(-1) - px.radii[pts][tbl]
            ni, mi = np.nonzero((lbp < gap[fi][:, None]) & tab["valid"][bi])
            if not len(ni):
                continue
            cf, ch, cp = fi[ni], hi[ni], tbl[ni, mi]
            rh = r_h[cf, ch]
            xw = x[frames[cf], cp]
            xl = np.einsum("nba,nb->na", rh, xw - p_h[cf, ch])  # hull-body frame
            value, normal_l = (self.planes(xl, ch, self.exact_planes[k]) if self.planes is not None
                               else max_planes(xl, ch, *self.plane_tables[k]))
            value -= px.radii[pts][cp]
            order = np.lexsort((cp, value, ch, cf))  # per (frame, hull): the least value, first point
            key = cf[order] * len(hulls) + ch[order]
            first = order[np.r_[True, key[1:] != key[:-1]]]
            short = np.maximum(gap[cf[first]] - value[first], 0.0)
            r[frames[cf[first]], row0 + ch[first]] = sw * short
            a = first[short > 0]
            if len(a):
                act_f.append(frames[cf[a]])
                act_row.append(row0 + ch[a])
                act_x.append(xw[a])
                act_n.append(np.einsum("fab,fb->fa", rh[a], normal_l[a]))
                act_pb.append(pcol[cp[a]])
                act_hb.append(hcol[ch[a]])
        cat = lambda v, shape: np.concatenate(v) if v else np.zeros(shape)  # noqa: E731
        f, rows_, x, n = cat(act_f, 0).astype(np.int64), cat(act_row, 0).astype(np.int64), cat(act_x, (0, 3)), cat(act_n, (0, 3))
        pb, hb = cat(act_pb, 0).astype(np.int64), cat(act_hb, 0).astype(np.int64)

        def jacobian(z: np.ndarray, o: np.ndarray) -> np.ndarray:
            jac = np.zeros((t, self.width, z.shape[1]))
            if len(f):
                moves = (pose.mask[:, pb] - pose.mask[:, hb]).T  # (A,J)
                jac[f, rows_] = -sw * normal_jacobian(z, o, f, x, n) * moves
            return jac

        return r, jacobian


#: planes per hull in the exact cull's lower bound
_BOUND_PLANES = 14


@njit(cache=True, nogil=True)
def _closest(frames, gap, x, centre, c_radius, table, p_radius, rot, pos, hcol, bounds,
             planes, plane_count):  # pragma: no cover (compiled)
    """Per frame f of `frames` (gap (F,) > 0) and hull h of a pair: the least max-plane value
    (polytope distance − point radius) over the hand's points below the gap (inf: none), that
    point (the first of equal values) and its plane's normal (hull frame). The NumPy form's cull
    in the same order: a cluster's ball against the hull's bound planes, then each point's own
    bound, then the point's full plane set. x (T,P,3) world points, centre (T,nc,3) the
    clusters' ball centres (radius c_radius), table (nc,m) their points (−1: padding), rot/pos
    the FK pass, hcol (H,) the hulls' FK bodies, bounds (H,K,4), planes (H,F,4) / plane_count."""
    n_f, n_h, n_k = len(frames), len(hcol), bounds.shape[1]
    value = np.full((n_f, n_h), np.inf)
    point = np.zeros((n_f, n_h), np.int64)
    normal = np.zeros((n_f, n_h, 3))
    nw = np.empty((n_k, 3))
    dw = np.empty(n_k)
    for i in range(n_f):
        t, g = frames[i], gap[i]
        for h in range(n_h):
            b = hcol[h]
            for k in range(n_k):  # the bound planes in the world: n_w = R n, d_w = d − p·n_w
                for a in range(3):
                    nw[k, a] = rot[t, b, a, 0] * bounds[h, k, 0] + rot[t, b, a, 1] * bounds[h, k, 1] \
                        + rot[t, b, a, 2] * bounds[h, k, 2]
                dw[k] = bounds[h, k, 3] - (pos[t, b, 0] * nw[k, 0] + pos[t, b, 1] * nw[k, 1] + pos[t, b, 2] * nw[k, 2])
            best, best_p, face = np.inf, -1, 0
            for c in range(len(table)):
                lb = -np.inf
                for k in range(n_k):
                    lb = max(lb, centre[t, c, 0] * nw[k, 0] + centre[t, c, 1] * nw[k, 1] + centre[t, c, 2] * nw[k, 2] + dw[k])
                if not lb - c_radius[c] < g:
                    continue
                for m in range(table.shape[1]):
                    p = table[c, m]
                    if p < 0:
                        continue
                    lbp = -np.inf
                    for k in range(n_k):
                        lbp = max(lbp, x[t, p, 0] * nw[k, 0] + x[t, p, 1] * nw[k, 1] + x[t, p, 2] * nw[k, 2] + dw[k])
                    if not lbp - p_radius[p] < g:
                        continue
                    v0, v1, v2 = x[t, p, 0] - pos[t, b, 0], x[t, p, 1] - pos[t, b, 1], x[t, p, 2] - pos[t, b, 2]
                    l0 = rot[t, b, 0, 0] * v0 + rot[t, b, 1, 0] * v1 + rot[t, b, 2, 0] * v2  # Rᵀ(x − p)
                    l1 = rot[t, b, 0, 1] * v0 + rot[t, b, 1, 1] * v1 + rot[t, b, 2, 1] * v2
                    l2 = rot[t, b, 0, 2] * v0 + rot[t, b, 1, 2] * v1 + rot[t, b, 2, 2] * v2
                    top, f_top = -np.inf, 0
                    for f in range(plane_count[h]):
                        sd = (l0 * planes[h, f, 0] + l1 * planes[h, f, 1] + l2 * planes[h, f, 2]) + planes[h, f, 3]
                        if f == 0 or sd > top:
                            top, f_top = sd, f
                    v = top - p_radius[p]
                    if v < g and (v < best or (v == best and p < best_p)):
                        best, best_p, face = v, p, f_top
            if best_p >= 0:
                value[i, h] = best
                point[i, h] = best_p
                for a in range(3):
                    normal[i, h, a] = planes[h, face, a]
    return value, point, normal


def _unpadded(planes: np.ndarray) -> np.ndarray:
    """A hull's planes without the padding (`Proxies.hull_planes` repeats the first plane at the
    end): the argmax, and so the face, stays the first maximal plane."""
    n = len(planes)
    while n > 1 and np.array_equal(planes[n - 1], planes[0]):
        n -= 1
    return planes[:n]


def _hand_table(px, pts: np.ndarray) -> dict[str, np.ndarray]:
    """A hand's points in clusters of ≤ `_CLUSTER` points on one body (each body's points split in
    halves along their widest axis): `body` (proxy body of each cluster), `slot` (each point's
    cluster), a padded (nc, m) `table` of indices into `pts` (`valid`: not padding), the points in
    their body's frame (`local`, (nc,3,m)) and each cluster's ball (`centre`, `radius`; the radius
    a little large, so the normals' rounding (|n| = 1 ± 1e-9) cannot make the bound inexact)."""
    clusters: list[np.ndarray] = []
    for b in np.unique(px.sphere_body[pts]):
        on_b = np.flatnonzero(px.sphere_body[pts] == b)
        clusters += [on_b[k] for k in median_cuts(px.centres[pts[on_b]], _CLUSTER)]
    width = max(len(k) for k in clusters)
    table = np.full((len(clusters), width), -1, dtype=np.int64)
    local = np.zeros((len(clusters), 3, width))
    centre, radius = np.zeros((len(clusters), 3)), np.zeros(len(clusters))
    slot = np.zeros(len(pts), dtype=np.int64)
    for i, k in enumerate(clusters):
        table[i, : len(k)] = k
        slot[k] = i
        c = px.centres[pts[k]]
        local[i, :, : len(k)] = c.T
        centre[i] = (c.min(0) + c.max(0)) / 2
        radius[i] = (np.linalg.norm(c - centre[i], axis=1) + px.radii[pts[k]]).max() * (1 + 1e-6) + 1e-9
    body = np.array([px.sphere_body[pts[k[0]]] for k in clusters])
    return dict(body=body, slot=slot, table=table, valid=table >= 0, local=local, centre=centre, radius=radius)


#: most points per cluster of the hand-clearance cull
_CLUSTER = 20


def _spread(normals: np.ndarray, n: int) -> np.ndarray:
    """Indices of `n` planes whose normals are spread over the sphere (farthest-point order)."""
    _, keep = np.unique(np.round(normals, 9), axis=0, return_index=True)
    chosen = [int(keep[0])]
    d = np.full(len(normals), np.inf)
    for _ in range(min(n, len(keep)) - 1):
        d = np.minimum(d, np.linalg.norm(normals - normals[chosen[-1]], axis=1))
        chosen.append(int(d.argmax()))
    return np.array(sorted(set(chosen)), dtype=np.int64)


def hand_clearance_term(robot: Robot, targets, w: float) -> HandClearanceTerm | None:
    """The term for `targets` (None when no frame asks for a clearance or `w` is 0)."""
    gap = getattr(targets, "hand_gap", None)
    if gap is None or w <= 0 or not np.any(np.asarray(gap) > 0) or not robot.spec.proxy_pairs:
        return None
    if not all(f"{s}_wrist" in robot.spec.landmarks for s in SIDES):
        return None
    return HandClearanceTerm(robot, gap, w)
