"""Whole-sequence IK: reaches reachable targets, keeps limits, removes a planted hand-hand collision."""

import numpy as np
import pytest
import torch

from embody.config.ik import IKConfig
from embody.retarget.banded import block_pentadiagonal_solve
from embody.retarget.costs import Residuals
from embody.retarget.ik import IKSolution, solve
from embody.retarget.limits import clamp_velocity, velocity_violations
from embody.retarget.targets import Targets, robot_arm_length
from embody.retarget.verify import self_collision_contacts, verify
from embody.config.robot import RobotConfig
from embody.robot import load_robot


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _targets_from_q(robot, q: np.ndarray, fps: float = 30.0) -> Targets:
    with torch.no_grad():
        p, r = robot.link_points(torch.tensor(q), ["left_wrist", "right_wrist", "left_elbow", "right_elbow"])
    t = len(q)
    eye = np.tile(np.eye(3), (t, 1, 1))
    return Targets(wrist_pos=p[:, :2].numpy(), wrist_rot=r[:, :2].numpy(), elbow_pos=p[:, 2:].numpy(),
                   torso_rot=eye, head_rot=eye, hand_q=np.zeros((t, 0)), hand_joints=[], fps=fps,
                   arm_length=robot_arm_length(robot))


def _smooth_random_q(robot, t: int, seed: int) -> np.ndarray:
    """Smooth random arm motion around a signing-like pose (half-way between rest and T-pose)."""
    rng = np.random.default_rng(seed)
    ik = np.flatnonzero(robot.ik_mask)
    amp, phase = rng.uniform(-0.4, 0.4, len(ik)), rng.uniform(0, 2 * np.pi, len(ik))
    s = np.linspace(0, 1, t)[:, None]
    q = np.tile((robot.rest + robot.tpose) / 2, (t, 1))
    q[:, ik] += amp * np.sin(np.pi * s + phase)
    return robot.clip(q)


def test_reaches_reachable_targets_within_limits(robot):
    targets = _targets_from_q(robot, _smooth_random_q(robot, 24, seed=1))
    sol = solve(robot, targets, IKConfig())
    assert sol.q.shape == (24, robot.n_joints)
    assert sol.metrics["wrist_pos_err_mm"] < 5.0
    assert sol.metrics["wrist_rot_err_deg"] < 3.0
    assert np.all(sol.q >= robot.lower) and np.all(sol.q <= robot.upper)
    assert sol.metrics["joint_limit_violations"] == 0
    assert sol.metrics["velocity_violations"] == 0
    # 24 frames at 30 fps span 23/30 s → 39 samples at 50 Hz
    assert sol.q_control.shape == (39, robot.n_joints)
    # warm start from the previous solution converges at least as well
    again = solve(robot, targets, IKConfig(iterations=5), init=sol)
    assert again.metrics["wrist_pos_err_mm"] <= sol.metrics["wrist_pos_err_mm"] + 0.5
    back = IKSolution.from_arrays(sol.to_arrays(), sol.to_attrs())
    assert np.array_equal(back.q, sol.q) and back.metrics == sol.metrics


def test_unreachable_targets_never_violate_limits(robot):
    targets = _targets_from_q(robot, np.tile(robot.tpose, (4, 1)))
    targets.wrist_pos = targets.wrist_pos * 3.0  # far out of reach
    sol = solve(robot, targets, IKConfig(iterations=15))
    assert np.all(sol.q >= robot.lower) and np.all(sol.q <= robot.upper)


def test_removes_planted_hand_collision(robot):
    # From the rest pose (forearms forward), both wrists asked 10 cm apart in front of the chest:
    # the hands (thumbs inwards) would overlap by a few centimetres.
    targets = _targets_from_q(robot, np.tile(robot.rest, (4, 1)))
    targets.wrist_pos[:, 0] = [0.30, 0.05, 0.10]
    targets.wrist_pos[:, 1] = [0.30, -0.05, 0.10]
    naive = solve(robot, targets, IKConfig(w_collision=0.0, contact_repair=False))
    assert self_collision_contacts(robot, naive.q).sum() > 0  # the plant really collides
    sol = solve(robot, targets, IKConfig(contact_repair=False))  # the proxies alone
    table, metrics = verify(robot, sol, targets)
    assert metrics["self_collision_frames"] == 0
    assert (table["self_contacts"] == 0).all()
    assert table["wrist_pos_err_mm_left"].max() < 40.0  # still close to the target
    assert solve(robot, targets, IKConfig()).q.tobytes() == sol.q.tobytes()  # deterministic


def test_velocity_clamp():
    q = np.zeros((5, 2))
    q[2:] = 1.0
    out = clamp_velocity(q, np.array([3.0, 30.0]), fps=10.0)
    assert velocity_violations(out, np.array([3.0, 30.0]), 10.0) == 0
    assert np.allclose(out[:, 0], [0, 0, 0.3, 0.6, 0.9]) and np.allclose(out[:, 1], q[:, 1])


@pytest.mark.parametrize("t", [1, 2, 7, 8])
def test_block_pentadiagonal_solve_matches_dense(t):
    rng = np.random.default_rng(t)
    n = 3
    jac = rng.normal(size=(t, n + 2, n))
    diag = np.einsum("tmi,tmj->tij", jac, jac) + np.eye(n)
    off1 = rng.uniform(-0.4, 0.0, size=(max(t - 1, 0), n))
    off2 = rng.uniform(0.0, 0.1, size=(max(t - 2, 0), n))
    dense = np.zeros((t * n, t * n))
    for k, blocks in ((0, diag), (1, [np.diag(o) for o in off1]), (2, [np.diag(o) for o in off2])):
        for i, blk in enumerate(blocks):
            dense[i * n:(i + 1) * n, (i + k) * n:(i + k + 1) * n] = blk
            dense[(i + k) * n:(i + k + 1) * n, i * n:(i + 1) * n] = blk.T
    rhs = rng.normal(size=(t, n))
    x = block_pentadiagonal_solve(diag, off1, off2, rhs)
    assert np.allclose(dense @ x.reshape(-1), rhs.reshape(-1), atol=1e-10)


def test_residual_jacobian_matches_finite_differences(robot):
    # hands pressed together in front of the chest and an arm against the torso: every term active
    q = _smooth_random_q(robot, 3, seed=4)
    q[:, robot.joint_index("left_shoulder_roll_joint")] = -0.25
    targets = _targets_from_q(robot, q)
    targets.wrist_pos = targets.wrist_pos + 0.03  # non-zero position and rotation residuals
    res = Residuals(robot, targets, IKConfig(w_torso_rot=0.0))  # the 18 rows: wrists, elbows, wrist rotations
    r, jac = res(q, jacobian=True)
    assert r.shape[1] > 4 * 3 + 2 * 3  # collision rows are present
    ik = res.ik
    eps = 1e-6
    fd = np.zeros_like(jac)
    for k, j in enumerate(ik):
        qp, qm = q.copy(), q.copy()
        qp[:, j] += eps
        qm[:, j] -= eps
        rp, _ = res(qp)
        rm, _ = res(qm)
        if rp.shape == r.shape and rm.shape == r.shape:
            fd[:, :, k] = (rp - rm) / (2 * eps)
    # position rows exact; rotation rows (log map) exact at zero rotation error, as here
    assert np.allclose(jac[:, :18], fd[:, :18], atol=1e-5)
    col = slice(18, None)
    assert np.abs(jac[:, col]).max() > 0 and np.allclose(jac[:, col], fd[:, col], atol=1e-4)


def test_metrics_carry_mujoco_verdict(robot):
    targets = _targets_from_q(robot, _smooth_random_q(robot, 12, seed=2))
    sol = solve(robot, targets, IKConfig(iterations=8))
    _, checked = verify(robot, sol.q, targets)
    for key in ("self_collision_frames", "limit_violations", "velocity_violations", "wrist_pos_mean_mm",
                "wrist_pos_p95_mm", "wrist_rot_mean_deg", "elbow_pos_err_mm", "jerk"):
        assert sol.metrics[key] == pytest.approx(checked[key]), key
    assert sol.frame_metrics["self_contacts"].shape == (12,)


def test_velocity_limits_respected_inside_the_solve(robot):
    # a target jump the velocity limits cannot follow in one frame: no violations either way,
    # but the solve spreads the move around the jump instead of lagging behind a clamp
    q = np.tile((robot.rest + robot.tpose) / 2, (16, 1))
    q[8:, robot.joint_index("left_elbow_joint")] += 0.8  # 5 frames' worth of the 5 rad/s limit
    targets = _targets_from_q(robot, robot.clip(q))
    sol = solve(robot, targets, IKConfig(w_collision=0.0, w_smooth=0.0))
    clamped = solve(robot, targets, IKConfig(w_collision=0.0, w_smooth=0.0, w_velocity=0.0))
    assert sol.metrics["velocity_violations"] == 0 and clamped.metrics["velocity_violations"] == 0
    err = sol.frame_metrics["wrist_pos_err_mm"][:, 0]
    assert err.max() < 0.5 * clamped.frame_metrics["wrist_pos_err_mm"][:, 0].max()


def test_sphere_pair_jacobian_on_h1():
    # H1's proxies are sphere covers: their clearance rows get the same finite-difference check
    robot = load_robot(RobotConfig(name="unitree_h1"))
    rng = np.random.default_rng(0)
    q = rng.uniform(robot.lower, robot.upper, size=(64, robot.n_joints))
    targets = _targets_from_q(robot, q)
    res = Residuals(robot, targets, IKConfig())
    r, jac = res(q, jacobian=True)
    col = slice(18, None)
    assert r.shape[1] > 18 and np.abs(jac[:, col]).max() > 0
    eps = 1e-6
    for k, j in enumerate(res.ik):
        qp, qm = q.copy(), q.copy()
        qp[:, j] += eps
        qm[:, j] -= eps
        rp, rm = res(qp)[0], res(qm)[0]
        assert rp.shape == r.shape and rm.shape == r.shape
        fd = (rp[:, col] - rm[:, col]) / (2 * eps)
        active = (r[:, col] > 1e-4) & (rp[:, col] > 0) & (rm[:, col] > 0)  # away from the hinge kink
        assert np.allclose(jac[:, col, k][active], fd[active], atol=1e-4)


def test_pytorch_kinematics_backend_matches_tree(robot):
    # same residuals and Jacobians to round-off, so the same LM iterations and the same q
    targets = _targets_from_q(robot, _smooth_random_q(robot, 12, seed=5))
    pk_sol = solve(robot, targets, IKConfig(kinematics="pytorch_kinematics"))
    tree_sol = solve(robot, targets, IKConfig(kinematics="tree"))
    assert pk_sol.metrics["wrist_pos_err_mm"] < 5.0
    assert np.all(pk_sol.q >= robot.lower) and np.all(pk_sol.q <= robot.upper)
    assert pk_sol.metrics["joint_limit_violations"] == 0 and pk_sol.metrics["velocity_violations"] == 0
    assert np.abs(pk_sol.q - tree_sol.q).max() < 1e-6
    q = _smooth_random_q(robot, 12, seed=4)  # away from the solution: every residual non-zero
    r_pk, j_pk = Residuals(robot, targets, IKConfig(kinematics="pytorch_kinematics"))(q, jacobian=True)
    r_tree, j_tree = Residuals(robot, targets, IKConfig(kinematics="tree"))(q, jacobian=True)
    assert r_pk.shape == r_tree.shape and np.abs(r_pk - r_tree).max() < 1e-9
    assert np.abs(j_pk - j_tree).max() < 1e-9


def test_collision_scale_weights_the_proxy_term(robot):
    # the tracking phase's faint collision term: residual rows and Jacobian scale by √scale
    q = _smooth_random_q(robot, 3, seed=4)
    q[:, robot.joint_index("left_shoulder_roll_joint")] = -0.25
    res = Residuals(robot, _targets_from_q(robot, q), IKConfig(w_torso_rot=0.0))  # 18 tracking rows
    full, jf = res(q, jacobian=True)
    faint, jt = res(q, jacobian=True, collision=1e-3)
    off, _ = res(q, collision=0.0)
    assert full.shape == faint.shape and off.shape[1] == 18 < full.shape[1]
    assert np.allclose(faint[:, 18:], full[:, 18:] * 1e-3**0.5, rtol=1e-12)
    assert np.allclose(jt[:, 18:], jf[:, 18:] * 1e-3**0.5, rtol=1e-12)
    assert np.array_equal(faint[:, :18], full[:, :18])
