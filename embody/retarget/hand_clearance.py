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

import numpy as np

from embody.metrics.fidelity import hand_length, hand_ratio  # noqa: F401  (re-exported: one definition)
from embody.robot import Robot
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

    def __init__(self, robot: Robot, gap: np.ndarray, w: float) -> None:
        px = robot_proxies(robot)
        self.gap = np.asarray(gap, dtype=np.float64).reshape(len(gap), -1)
        self.w = float(w)
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
        self.pairs = [(0, points["left"], hulls["right"]), (0, points["right"], hulls["left"]),
                      (1, points["left"], chest), (2, points["right"], chest),
                      (3, points["left"], face), (4, points["right"], face)]
        self.pairs = [(c, p, h) for c, p, h in self.pairs if c < self.gap.shape[1] and len(p) and len(h)]
        self.px = px
        used = {px.bodies[b] for _, p, h in self.pairs for b in np.r_[px.sphere_body[p]]}
        used |= {px.bodies[b] for _, p, h in self.pairs for b in px.hull_body[h]}
        #: bodies the FK must walk (the costs add them to their body set)
        self.bodies = sorted(used)
        #: one row per (pair, hull)
        self.width = sum(len(h) for _, _, h in self.pairs)
        #: per hull, a few planes of well-spread normals: their max is a lower bound of the
        #: hull's max-plane value (every plane is), so points it puts at ≥ the gap are culled exactly
        self.bound_planes = {h: px.hull_planes[h][_spread(px.hull_planes[h][:, :3], _BOUND_PLANES)]
                             for _, _, hulls in self.pairs for h in hulls}

    def _points(self, pose, frames: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px = self.px
        col = np.array([pose.index[px.bodies[b]] for b in px.sphere_body[pts]])
        x = pose.pos[frames][:, col] + np.einsum("fpab,pb->fpa", pose.rot[frames][:, col], px.centres[pts])
        return x, col

    def _near(self, pose, frames: np.ndarray, x: np.ndarray, pts: np.ndarray, hulls: np.ndarray,
              gap: np.ndarray, slack: float = 0.01) -> np.ndarray:
        """Broad phase: which of `frames` have the bounding sphere of the points `x` (F,P,3) within
        `gap` (+ slack) of some hull's bounding sphere."""
        px = self.px
        c = x.mean(1)
        r = np.linalg.norm(x - c[:, None], axis=-1).max(1) + px.radii[pts].max(initial=0.0)
        hcol = np.array([pose.index[px.bodies[px.hull_body[h]]] for h in hulls])
        hc = pose.pos[frames][:, hcol] + np.einsum("fhab,hb->fha", pose.rot[frames][:, hcol], px.hull_centre[hulls])
        apart = (np.linalg.norm(hc - c[:, None], axis=-1) - px.hull_radius[hulls][None]).min(1) - r - slack
        return apart < gap

    def rows(self, pose, scale: float) -> tuple[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """The IK's `ResidualTerm` protocol (`costs.py`); phased in with the collision term
        (`scale`), since both keep parts apart."""
        sw = np.sqrt(max(self.w * float(scale), 0.0))
        if sw == 0.0 or not self.pairs:
            return None
        t, px = len(pose.rot), self.px
        r = np.zeros((t, self.width))
        act_f, act_row, act_x, act_n, act_pb, act_hb = [], [], [], [], [], []
        row = 0
        for c, pts, hulls in self.pairs:
            frames = np.flatnonzero(self.gap[:, c] > 0)
            x, pcol = self._points(pose, frames, pts)  # once: the broad phase and the rows share it
            if len(frames):
                near = self._near(pose, frames, x, pts, hulls, self.gap[frames, c])
                frames, x = frames[near], x[near]
            if not len(frames):
                row += len(hulls)
                continue
            radii, gap = px.radii[pts], self.gap[frames, c]
            for h in hulls:
                hcol = pose.index[px.bodies[px.hull_body[h]]]
                r_h, p_h = pose.rot[frames, hcol], pose.pos[frames, hcol]
                planes, bound = px.hull_planes[h], self.bound_planes[h]
                # exact cull: a point whose lower bound is ≥ the gap cannot shorten it (the bound
                # planes taken to the world, n_w = R n, d_w = d − n_w·p, so no point is moved)
                n_w = np.einsum("fab,kb->fka", r_h, bound[:, :3])
                d_w = bound[:, 3] - np.einsum("fka,fa->fk", n_w, p_h)
                lb = (np.matmul(x, n_w.transpose(0, 2, 1)) + d_w[:, None]).max(-1) - radii[None]
                fi, pi = np.nonzero(lb < gap[:, None])
                if len(fi):
                    xl = np.einsum("nba,nb->na", r_h[fi], x[fi, pi] - p_h[fi])  # hull-body frame
                    sd = xl @ planes[:, :3].T + planes[:, 3]
                    face = sd.argmax(-1)
                    value = sd[np.arange(len(fi)), face] - radii[pi]
                    order = np.lexsort((pi, value, fi))  # per frame: the least value, first point
                    first = order[np.r_[True, fi[order][1:] != fi[order][:-1]]]
                    a_f, a_p = fi[first], pi[first]
                    short = np.maximum(gap[a_f] - value[first], 0.0)
                    r[frames[a_f], row] = sw * short
                    a = short > 0
                    if a.any():
                        act_f.append(frames[a_f[a]])
                        act_row.append(np.full(int(a.sum()), row))
                        act_x.append(x[a_f[a], a_p[a]])
                        act_n.append(np.einsum("fab,fb->fa", r_h[a_f[a]], planes[face[first[a]], :3]))
                        act_pb.append(pcol[a_p[a]])
                        act_hb.append(np.full(int(a.sum()), hcol))
                row += 1
        cat = lambda v, shape: np.concatenate(v) if v else np.zeros(shape)  # noqa: E731
        f, rows_, x, n = cat(act_f, 0).astype(np.int64), cat(act_row, 0).astype(np.int64), cat(act_x, (0, 3)), cat(act_n, (0, 3))
        pb, hb = cat(act_pb, 0).astype(np.int64), cat(act_hb, 0).astype(np.int64)

        def jacobian(z: np.ndarray, o: np.ndarray) -> np.ndarray:
            jac = np.zeros((t, self.width, z.shape[1]))
            if len(f):
                arm = np.cross(z[f], x[:, None] - o[f])  # (A,J,3)
                moves = (pose.mask[:, pb] - pose.mask[:, hb]).T  # (A,J)
                jac[f, rows_] = -sw * np.einsum("ac,ajc->aj", n, arm) * moves
            return jac

        return r, jacobian


#: planes per hull in the exact cull's lower bound
_BOUND_PLANES = 14


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
