"""`same_problem`: when two target sets give the IK exactly the same problem, one solve serves both
(the pipeline reuses the retarget step's solve as the IK-only fidelity baseline)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from embody.config.ik import IKConfig
from embody.retarget.ik import same_problem, solve
from embody.retarget.targets import Targets, robot_arm_length
from embody.robot import load_robot


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _targets(robot, t: int = 10) -> Targets:
    q = np.tile((robot.rest + robot.tpose) / 2, (t, 1))
    ik = np.flatnonzero(robot.ik_mask)
    q[:, ik] += 0.2 * np.sin(np.linspace(0, 1, t))[:, None]
    with torch.no_grad():
        p, r = robot.link_points(torch.tensor(robot.clip(q)), ["left_wrist", "right_wrist", "left_elbow", "right_elbow"])
    eye = np.tile(np.eye(3), (t, 1, 1))
    return Targets(wrist_pos=p[:, :2].numpy(), wrist_rot=r[:, :2].numpy(), elbow_pos=p[:, 2:].numpy(),
                   torso_rot=eye, head_rot=eye, hand_q=np.zeros((t, 0)), hand_joints=[], fps=30.0,
                   arm_length=robot_arm_length(robot))


def test_unanchored_points_pose_the_same_problem(robot):
    plain = _targets(robot)
    names = list(robot.spec.landmarks)[:2]
    idle = replace(plain, point_names=names, point_pos=np.ones((len(plain.wrist_pos), 2, 3)),
                   point_weight=np.zeros((len(plain.wrist_pos), 2)))
    assert same_problem(plain, idle) and same_problem(idle, plain)
    cfg = IKConfig(iterations=4, tracking_iterations=2)
    assert np.array_equal(solve(robot, plain, cfg).q, solve(robot, idle, cfg).q)


def test_any_solver_input_difference_is_a_different_problem(robot):
    plain = _targets(robot)
    moved = replace(plain, wrist_pos=plain.wrist_pos.copy())
    moved.wrist_pos[3, 0, 1] += 1e-6
    assert not same_problem(plain, moved)
    released = replace(plain, wrist_weight=np.ones((len(plain.wrist_pos), 2)))
    released.wrist_weight[0, 1] = 0.5
    assert not same_problem(plain, released)
    names = list(robot.spec.landmarks)[:1]
    weight = np.zeros((len(plain.wrist_pos), 1))
    weight[4] = 0.3
    anchored = replace(plain, point_names=names, point_pos=np.zeros((len(weight), 1, 3)), point_weight=weight)
    assert not same_problem(plain, anchored) and same_problem(anchored, replace(anchored))
    assert not same_problem(anchored, replace(anchored, point_weight=weight * 2))
