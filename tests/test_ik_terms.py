"""Extra IK residual terms slot into the solver's residual list with their own FK bodies."""

import numpy as np
import pytest

from embody.config.ik import IKConfig
from embody.retarget.costs import Pose, ResidualTerm, Residuals, point_jacobian
from embody.robot import load_robot


class _PalmPoint(ResidualTerm):
    """A point on the left wrist-yaw body pulled towards a fixed torso-frame target."""

    bodies = ["left_wrist_yaw_link"]

    def __init__(self, target: np.ndarray, offset: np.ndarray) -> None:
        self.target, self.offset = target, offset

    def rows(self, pose: Pose, scale: float):
        b = pose.index["left_wrist_yaw_link"]
        p = (pose.pos[:, b] + pose.rot[:, b] @ self.offset)[:, None]  # (T,1,3)
        moves = pose.mask[:, [b]]
        return (p - self.target)[:, 0], lambda z, o: point_jacobian(z, o, p, moves)[:, 0]


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def test_extra_term_rows_and_jacobian_match_finite_differences(robot):
    from tests.test_retarget_ik import _smooth_random_q, _targets_from_q

    q = _smooth_random_q(robot, 3, seed=7)
    targets = _targets_from_q(robot, q)
    cfg = IKConfig(w_collision=0.0, w_torso_rot=0.0)
    plain = Residuals(robot, targets, cfg)
    term = _PalmPoint(np.array([0.3, 0.1, 0.0]), np.array([0.09, -0.017, 0.0]))
    res = Residuals(robot, targets, cfg, terms=[term])
    r0, j0 = plain(q, jacobian=True)
    r, jac = res(q, jacobian=True)
    assert r.shape[1] == r0.shape[1] + 3 and np.array_equal(r[:, :-3], r0)
    assert np.array_equal(jac[:, :-3], j0)
    eps = 1e-6
    for k, j in enumerate(res.ik):
        qp, qm = q.copy(), q.copy()
        qp[:, j] += eps
        qm[:, j] -= eps
        fd = (res(qp)[0][:, -3:] - res(qm)[0][:, -3:]) / (2 * eps)
        assert np.allclose(jac[:, -3:, k], fd, atol=1e-6)
    assert np.abs(jac[:, -3:]).max() > 0.05  # the arm joints really move the point
