"""IK residual keeping the robot's hands apart where the human's hands are apart (at hand scale).

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
the touch a touch without penetration. The fidelity measure judges robot contacts at the same
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


class HandClearanceTerm:
    """Hinge rows √(w·scale)·relu(gap(t) − d_h(q)), one per hull h of either hand (d_h: the
    other hand's closest proxy point to it), for frames with gap > 0."""

    def __init__(self, robot: Robot, gap: np.ndarray, w: float) -> None:
        px = robot_proxies(robot)
        self.gap = np.asarray(gap, dtype=np.float64)
        self.w = float(w)
        m = robot.model
        hand: dict[str, set[str]] = {}
        for s in SIDES:
            sub = subtree_ids(m, robot.spec.landmarks[f"{s}_wrist"].body)
            hand[s] = {m.body(b).name for b in sub}
        in_hand = lambda names, s: np.array([px.bodies[b] in hand[s] for b in names], dtype=bool)  # noqa: E731
        self.points = {s: np.flatnonzero(in_hand(px.sphere_body, s)) for s in SIDES}
        self.hulls = {s: np.flatnonzero(in_hand(px.hull_body, s)) for s in SIDES}
        self.px = px
        used = {px.bodies[b] for s in SIDES for b in px.sphere_body[self.points[s]]}
        used |= {px.bodies[b] for s in SIDES for b in px.hull_body[self.hulls[s]]}
        #: bodies the FK must walk (the costs add them to their body set)
        self.bodies = sorted(used)

    def clearance(self, rot: np.ndarray, pos: np.ndarray, index: dict[str, int], frames: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per frame in `frames` and per hull of either hand (H of them): the closest proxy point
        of the other hand, its clearance d (F,H), the point x and the hull's outward normal n
        (torso frame, (F,H,3)), and the FK columns of the point's and the hull's bodies (F,H).
        One row per hull, not only the closest pair: the solver sees every part that is short."""
        px = self.px
        d, xs, ns, pbs, hbs = [], [], [], [], []
        f_idx = np.arange(len(frames))
        for s, o in (("left", "right"), ("right", "left")):
            pts, hulls = self.points[s], self.hulls[o]
            if not len(pts) or not len(hulls):
                continue
            pcol = np.array([index[px.bodies[b]] for b in px.sphere_body[pts]])
            x = pos[frames][:, pcol] + np.einsum("fpab,pb->fpa", rot[frames][:, pcol], px.centres[pts])  # (F,P,3)
            for h in hulls:
                hcol = index[px.bodies[px.hull_body[h]]]
                r_h, p_h = rot[frames, hcol], pos[frames, hcol]
                xl = np.einsum("fba,fpb->fpa", r_h, x - p_h[:, None])  # hull-body frame
                planes = px.hull_planes[h]
                sd = xl @ planes[:, :3].T + planes[:, 3]  # (F,P,planes)
                face = sd.argmax(-1)
                value = np.take_along_axis(sd, face[..., None], -1)[..., 0] - px.radii[pts][None]
                k = value.argmin(1)
                d.append(value[f_idx, k])
                xs.append(x[f_idx, k])
                ns.append(np.einsum("fab,fb->fa", r_h, planes[face[f_idx, k], :3]))
                pbs.append(pcol[k])
                hbs.append(np.full(len(frames), hcol))
        return (np.stack(d, 1), np.stack(xs, 1), np.stack(ns, 1), np.stack(pbs, 1), np.stack(hbs, 1))

    def _near(self, pose, frames: np.ndarray, slack: float = 0.01) -> np.ndarray:
        """Broad phase: which of `frames` have the hands' bounding spheres (of their proxy
        points, plus `slack` for the hulls between points) within the asked gap."""
        px, c, rad = self.px, [], []
        for s in SIDES:
            pts = self.points[s]
            col = np.array([pose.index[px.bodies[b]] for b in px.sphere_body[pts]])
            x = pose.pos[frames][:, col] + np.einsum("fpab,pb->fpa", pose.rot[frames][:, col], px.centres[pts])
            c.append(x.mean(1))
            rad.append(np.linalg.norm(x - c[-1][:, None], axis=-1).max(1) + px.radii[pts].max(initial=0.0))
        apart = np.linalg.norm(c[0] - c[1], axis=-1) - rad[0] - rad[1] - 2 * slack
        return apart < self.gap[frames]

    def rows(self, pose, scale: float) -> tuple[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """The IK's `ResidualTerm` protocol (`costs.py`); phased in with the collision term
        (`scale`), since both keep hands apart."""
        t = len(pose.rot)
        frames = np.flatnonzero(self.gap > 0)
        sw = np.sqrt(max(self.w * float(scale), 0.0))
        if not len(frames) or sw == 0.0:
            return None
        frames = frames[self._near(pose, frames)]
        d, x, n, pb, hb = self.clearance(pose.rot, pose.pos, pose.index, frames)
        short = np.maximum(self.gap[frames, None] - d, 0.0)  # (F,H)
        r = np.zeros((t, d.shape[1]))
        r[frames] = sw * short
        fi, hi = np.nonzero(short > 0)

        def jacobian(z: np.ndarray, o: np.ndarray) -> np.ndarray:
            jac = np.zeros((t, d.shape[1], z.shape[1]))
            if len(fi):
                f = frames[fi]
                arm = np.cross(z[f], x[fi, hi][:, None] - o[f])  # (A,J,3)
                moves = (pose.mask[:, pb[fi, hi]] - pose.mask[:, hb[fi, hi]]).T  # (A,J)
                jac[f, hi] = -sw * np.einsum("aj,aj->aj", np.einsum("ac,ajc->aj", n[fi, hi], arm), moves)
            return jac

        return r, jacobian


def hand_clearance_term(robot: Robot, targets, w: float) -> HandClearanceTerm | None:
    """The term for `targets` (None when no frame asks for a clearance or `w` is 0)."""
    gap = getattr(targets, "hand_gap", None)
    if gap is None or w <= 0 or not np.any(np.asarray(gap) > 0) or not robot.spec.proxy_pairs:
        return None
    if not all(f"{s}_wrist" in robot.spec.landmarks for s in SIDES):
        return None
    return HandClearanceTerm(robot, gap, w)
