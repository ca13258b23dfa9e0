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


def test_block_banded_solve_with_a_jerk_band_matches_dense():
    from embody.retarget.banded import block_banded_solve

    rng = np.random.default_rng(3)
    t, n = 7, 3
    a = rng.normal(size=(t, n, n))
    diag = a @ np.swapaxes(a, 1, 2) + 20.0 * np.eye(n)
    offs = [rng.normal(size=(t - k, n)) for k in (1, 2, 3)]
    rhs = rng.normal(size=(t, n))
    dense = np.zeros((t * n, t * n))
    for i in range(t):
        dense[i * n:(i + 1) * n, i * n:(i + 1) * n] = diag[i]
    for k, off in enumerate(offs, 1):
        for i in range(t - k):
            block = np.diag(off[i])
            dense[i * n:(i + 1) * n, (i + k) * n:(i + k + 1) * n] = block
            dense[(i + k) * n:(i + k + 1) * n, i * n:(i + 1) * n] = block
    x = block_banded_solve(diag, offs, rhs)
    assert np.allclose(dense @ x.reshape(-1), rhs.reshape(-1), atol=1e-10)
    # the band factored in place (LAPACK pbsv, Fortran order) is scipy's solveh_banded, bit for bit
    from scipy.linalg import solveh_banded

    band = np.array([[dense[j + d, j] if j + d < t * n else 0.0 for j in range(t * n)] for d in range(3 * n + 1)])
    assert np.array_equal(x.reshape(-1), solveh_banded(band, rhs.reshape(-1), lower=True))


def test_jerk_term_lowers_jerk_of_a_noisy_target(robot):
    from embody.retarget.ik import solve
    from tests.test_retarget_ik import _smooth_random_q, _targets_from_q

    q = _smooth_random_q(robot, 30, seed=5)
    targets = _targets_from_q(robot, q)
    targets.wrist_pos = targets.wrist_pos + np.random.default_rng(0).normal(0, 0.004, targets.wrist_pos.shape)
    base = IKConfig(w_smooth=0.0, w_collision=0.0, contact_repair=False, iterations=12)
    plain = solve(robot, targets, base)
    smooth = solve(robot, targets, base.model_copy(update={"w_jerk": 0.05}))
    assert smooth.metrics["jerk"] < 0.7 * plain.metrics["jerk"]
    assert smooth.metrics["wrist_pos_err_mm"] < 10.0  # still tracks (noise is 4 mm per axis)


def test_cross_is_numpys_cross_bit_for_bit():
    """The IK's Jacobian levers use `jacobians.cross`: np.cross's values exactly, broadcast alike."""
    from embody.retarget.jacobians import cross
    rng = np.random.default_rng(3)
    for sa, sb in [((7, 3), (7, 3)), ((5, 1, 4, 3), (5, 6, 1, 3)), ((3,), (9, 2, 3))]:
        a, b = rng.normal(size=sa) * 10.0, rng.normal(size=sb)
        got, want = cross(a, b), np.cross(a, b)
        assert got.shape == want.shape and np.array_equal(got, want)
    assert not np.array_equal(cross(a, b), cross(b, a))  # its order matters, as np.cross's
