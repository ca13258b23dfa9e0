"""The cold start's coarse-to-fine pass (`ik.coarse_stride`) and collision continuation
(`ik.ramp_*`): the solution still reaches reachable targets, inside every limit, and stays
collision-free in MuJoCo."""

import numpy as np
import pytest
import torch

from embody.config.ik import IKConfig
from embody.retarget.ik import solve, solve_joints
from embody.retarget.targets import Targets, robot_arm_length
from embody.robot import load_robot


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _targets(robot, q: np.ndarray) -> Targets:
    with torch.no_grad():
        p, r = robot.link_points(torch.tensor(q), ["left_wrist", "right_wrist", "left_elbow", "right_elbow"])
    t = len(q)
    eye = np.tile(np.eye(3), (t, 1, 1))
    return Targets(wrist_pos=p[:, :2].numpy(), wrist_rot=r[:, :2].numpy(), elbow_pos=p[:, 2:].numpy(),
                   torso_rot=eye, head_rot=eye, hand_q=np.zeros((t, 0)), hand_joints=[], fps=30.0,
                   arm_length=robot_arm_length(robot))


def _motion(robot, t: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    ik = np.flatnonzero(robot.ik_mask)
    amp, phase = rng.uniform(-0.4, 0.4, len(ik)), rng.uniform(0, 2 * np.pi, len(ik))
    q = np.tile((robot.rest + robot.tpose) / 2, (t, 1))
    q[:, ik] += amp * np.sin(np.pi * np.linspace(0, 1, t)[:, None] + phase)
    return robot.clip(q)


@pytest.mark.parametrize("stride", [2, 3])
def test_coarse_cold_start_reaches_targets(robot, stride):
    targets = _targets(robot, _motion(robot, 31))  # 31 frames: the last coarse gap is shorter
    sol = solve(robot, targets, IKConfig(coarse_stride=stride))
    assert sol.metrics["wrist_pos_err_mm"] < 5.0
    assert sol.metrics["joint_limit_violations"] == 0 and sol.metrics["velocity_violations"] == 0
    assert sol.metrics["self_collision_frames"] == 0 and sol.metrics["control_self_collision_frames"] == 0


def test_coarse_pass_changes_only_the_start(robot):
    # the same problem from another start: both solves land on the reachable optimum
    targets = _targets(robot, _motion(robot, 24))
    fine = solve_joints(robot, targets, IKConfig(coarse_stride=1, ramp_iterations=0))
    coarse = solve_joints(robot, targets, IKConfig(coarse_stride=2))
    assert not np.array_equal(fine, coarse)  # the coarse path ran
    # redundant joints may settle elsewhere; the wrists land on the same targets
    pf, _ = robot.link_poses(fine, ["left_wrist", "right_wrist"])
    pc, _ = robot.link_poses(coarse, ["left_wrist", "right_wrist"])
    assert np.linalg.norm(pf - targets.wrist_pos, axis=-1).mean() < 0.005
    assert np.linalg.norm(pc - pf, axis=-1).max() < 0.005
