"""IK residual on robot hand points (palm centre, finger tips) placed relative to body landmarks.

A wrist target alone cannot put a fingertip on the chin: the robot's hand differs from the
human's (three fingers, other proportions), so the right wrist for the human's wrist offset still
leaves the tip centimetres off, and near G1's small head the wrist target is often unreachable
anyway. Here the point that carries the sign (the touching fingertip, the palm at the chest)
gets its own position target, √(w·weight)·(p(q) − a(q)), with the exact geometric Jacobian
(z × (p − o) for each IK hinge upstream of the point's body; finger joints are fixed at their
retargeted angles during the solve). Targets and per-frame weights come from
`targets.anchored_targets`: a point far from every landmark has weight 0 and this term vanishes.

The target a(q) rides on the robot's torso body (where the face and chest landmarks are): it is
stored in the torso frame at the target torso orientation and carried by the torso's actual pose,
so a waist that leans less (or more) than the human moves the target with the chin instead of
letting the solver lean the chin away from a fixed point.

Touch vs collision margin: the anchored target of a touching point lies at least
`ik.collision_margin` from its landmark (along the human's offset direction), which is the
clearance the self-collision term enforces between the proxies. The two terms then agree on where
the touch ends instead of pulling against each other: the robot touches at the margin and never
penetrates (MuJoCo measures such a touch at 1.3-1.7 cm between its hulls, within
`fidelity.robot_contact_eps`, the human's ε at hand scale).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from embody.retarget.jacobians import cross
from embody.robot import Robot


class HandPointTerm:
    """Weighted position residuals (T, 3P) of the robot landmark points `names` against (T,P,3)
    targets in the torso frame, per-frame weights (T,P) scaled by `w`."""

    def __init__(self, robot: Robot, names: list[str], target: np.ndarray, weight: np.ndarray,
                 torso_rot: np.ndarray, w: float) -> None:
        refs = [robot.spec.landmarks[n] for n in names]
        self.torso = robot.spec.torso_body
        #: bodies the FK must walk (the costs add them to their body set)
        self.bodies = [r.body for r in refs] + [self.torso]
        self.offset = np.array([r.offset for r in refs], dtype=np.float64).reshape(-1, 3)
        # the torso frame is the torso body's frame at the T-pose: anchor = torso_rotᵀ · target
        self.anchor = np.einsum("tba,tpb->tpa", np.asarray(torso_rot, dtype=np.float64),
                                np.asarray(target, dtype=np.float64))
        self.sw = np.sqrt(np.clip(w * np.asarray(weight, dtype=np.float64), 0.0, None))  # (T,P)

    def residual(self, rot: np.ndarray, pos: np.ndarray, index: dict[str, int]
                 ) -> tuple[np.ndarray, Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]]:
        """r (T,3P) from FK rotations/positions of the walked bodies, and J(axes, pivots, mask) (T,3P,J)
        where mask (J, walked bodies) says which IK joint moves which body."""
        b = [index[name] for name in self.bodies[:-1]]
        tb = index[self.torso]
        p = pos[:, b] + np.einsum("tpab,pb->tpa", rot[:, b], self.offset)
        a = pos[:, tb, None] + np.einsum("tab,tpb->tpa", rot[:, tb], self.anchor)
        r = ((p - a) * self.sw[..., None]).reshape(len(p), -1)

        def jacobian(z: np.ndarray, o: np.ndarray, mask: np.ndarray) -> np.ndarray:
            lever = lambda x: cross(z[:, None], x[:, :, None] - o[:, None])  # noqa: E731 (T,P,J,3)
            jac = lever(p) * mask[:, b].T[None, :, :, None] - lever(a) * mask[:, tb][None, None, :, None]
            jac = jac * self.sw[..., None, None]
            return jac.transpose(0, 1, 3, 2).reshape(len(p), -1, z.shape[1])

        return r, jacobian

    def rows(self, pose, scale: float) -> tuple[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]]:
        """The IK's `ResidualTerm` protocol (`costs.py`): rows from one FK pass `pose`; the
        collision phase factor `scale` does not apply to hand points."""
        r, jacobian = self.residual(pose.rot, pose.pos, pose.index)
        return r, lambda z, o: jacobian(z, o, pose.mask)


def hand_point_term(robot: Robot, targets, w: float) -> HandPointTerm | None:
    """The term for `targets` (None when it has no anchored hand points or `w` is 0)."""
    names = list(getattr(targets, "point_names", []) or [])
    if not names or w <= 0 or not np.any(targets.point_weight > 0):
        return None
    return HandPointTerm(robot, names, targets.point_pos, targets.point_weight, targets.torso_rot, w)
