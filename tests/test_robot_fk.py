"""Robot loading and FK parity: pytorch-kinematics chain, NumPy tree and mujoco.mj_kinematics."""

import mujoco
import numpy as np
import pytest
import torch

from embody.config.robot import RobotConfig
from embody.errors import ConfigError
from embody.robot import load_robot


@pytest.mark.parametrize("name,n_joints", [("unitree_g1_dex3", 43), ("unitree_h1", 19)])
def test_fk_matches_mujoco(name, n_joints):
    robot = load_robot(RobotConfig(name=name))
    assert robot.n_joints == n_joints
    rng = np.random.default_rng(0)
    qs = rng.uniform(robot.lower, robot.upper, size=(100, robot.n_joints))
    links = list(robot.spec.links)
    pos, rot = robot.link_points(torch.tensor(qs), links)
    data = mujoco.MjData(robot.model)
    base = robot.torso_from_world
    worst = 0.0
    for i, q in enumerate(qs):
        data.qpos[:] = robot.qpos(q)
        mujoco.mj_kinematics(robot.model, data)
        for k, link in enumerate(links):
            ref = robot.spec.links[link]
            b = robot.model.body(ref.body).id
            r = data.xmat[b].reshape(3, 3)
            p = data.xpos[b] + r @ np.array(ref.offset)
            p_t = base[:3, :3] @ p + base[:3, 3]
            worst = max(worst, np.abs(pos[i, k].numpy() - p_t).max(),
                        np.abs(rot[i, k].numpy() - base[:3, :3] @ r).max())
    assert worst <= 1e-9  # float64 offsets re-seated from MuJoCo (pk parses them in float32)


def test_limits_from_mujoco_and_tpose():
    robot = load_robot()
    assert robot.name == "unitree_g1_dex3"
    assert np.all(robot.lower < robot.upper)  # pk would report (0, 0) for unlimited joints
    assert np.all((robot.tpose >= robot.lower) & (robot.tpose <= robot.upper))
    assert len(robot.hand_joint_names("left")) == 7
    # T-pose: wrists straight out sideways at shoulder height, in the torso frame.
    pos, _ = robot.link_points(torch.tensor(robot.tpose)[None], ["left_shoulder", "left_wrist", "right_wrist"])
    assert pos[0, 1, 1] > 0.45 and pos[0, 2, 1] < -0.45
    assert abs(pos[0, 1, 2] - pos[0, 0, 2]) < 0.02
    assert robot.velocity_limits.min() > 0


def test_bad_robot_file_names_key(tmp_path):
    (tmp_path / "bad.yaml").write_text("mjcf: {file: unitree_g1/g1_with_hands.xml}\nroot_body: pelvis\n"
                                       "torso_body: torso_link\nlinks: {left_wrist: {body: nope}, "
                                       "right_wrist: {body: pelvis}}\nik_joints: ['*']\n")
    with pytest.raises(ConfigError, match="links.left_wrist.body"):
        load_robot(RobotConfig(name="bad", robots_dir=str(tmp_path)))
    (tmp_path / "typo.yaml").write_text("mjcf: {file: x.xml}\nroot_bdy: pelvis\n")
    with pytest.raises(ConfigError, match="typo.yaml"):
        load_robot(RobotConfig(name="typo", robots_dir=str(tmp_path)))
    with pytest.raises(ConfigError, match="robot.name"):
        load_robot(RobotConfig(name="missing", robots_dir=str(tmp_path)))


@pytest.mark.parametrize("name", ["unitree_g1_dex3", "unitree_h1"])
def test_fk_backends_agree_with_each_other_and_mujoco(name):
    robot = load_robot(RobotConfig(name=name))
    bodies = [robot.model.body(b).name for b in range(1, robot.model.nbody)]  # every body
    tree, chain = robot.fk(bodies, "tree"), robot.fk(bodies, "pytorch_kinematics")
    assert tree.names == chain.names and len(chain.names) == robot.model.nbody - 1
    rng = np.random.default_rng(1)
    qs = rng.uniform(robot.lower, robot.upper, size=(64, robot.n_joints))
    (r_t, p_t), (r_c, p_c) = tree.forward(qs), chain.forward(qs)
    assert np.abs(p_t - p_c).max() <= 1e-9 and np.abs(r_t - r_c).max() <= 1e-9
    ik = list(np.flatnonzero(robot.ik_mask))
    for a, b in zip(tree.joint_frames(r_t, p_t, ik), chain.joint_frames(r_c, p_c, ik)):
        assert np.abs(a - b).max() <= 1e-9
    assert np.array_equal(tree.moves(ik), chain.moves(ik))
    data = mujoco.MjData(robot.model)
    base = robot.torso_from_world
    for t in range(0, len(qs), 8):
        data.qpos[:] = robot.qpos(qs[t])
        mujoco.mj_kinematics(robot.model, data)
        ids = [robot.model.body(n).id for n in bodies]
        pos = data.xpos[ids] @ base[:3, :3].T + base[:3, 3]
        rot = base[:3, :3] @ data.xmat[ids].reshape(-1, 3, 3)
        assert np.abs(p_t[t] - pos).max() <= 1e-9 and np.abs(r_t[t] - rot).max() <= 1e-9


def test_unknown_fk_backend_is_a_config_error():
    with pytest.raises(ConfigError, match="ik.kinematics"):
        load_robot().fk(["torso_link"], "numba")


def test_chain_reuses_bodies_no_variable_joint_moves():
    """`variable` joints: the fingers and legs come from the cached relative transforms while
    the other joints keep their values, and are recomputed as soon as one of them changes."""
    robot = load_robot()
    ik = list(np.flatnonzero(robot.ik_mask))
    bodies = ["left_hand_index_1_link", "right_hand_thumb_2_link", "left_hip_roll_link", "torso_link",
              "left_elbow_link", "right_wrist_yaw_link"]
    full = robot.fk(bodies, "pytorch_kinematics")
    fast = robot.fk(bodies, "pytorch_kinematics", variable=ik)
    assert 0 < len(fast.reduced["keep"]) < len(fast.names)
    rng = np.random.default_rng(1)
    q = rng.uniform(robot.lower, robot.upper, size=(20, robot.n_joints))
    for step in range(3):
        if step == 1:  # only the IK joints move: the cached part is reused
            q[:, ik] = rng.uniform(robot.lower[ik], robot.upper[ik], size=(20, len(ik)))
        if step == 2:  # a finger moves: the cache is rebuilt
            j = robot.joint_index("left_hand_index_1_joint")
            q[:, j] = rng.uniform(robot.lower[j], robot.upper[j], size=20)
        for a, b in zip(full.forward(q), fast.forward(q)):
            np.testing.assert_allclose(b, a, atol=1e-12)
