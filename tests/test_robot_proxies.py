"""NumPy kinematic tree, collision proxies and MuJoCo contact counting on G1."""

import mujoco
import numpy as np
import pytest
import torch

from embody.robot import load_robot
from embody.robot.contacts import contact_pairs, self_collision_contacts
from embody.robot.proxies import robot_proxies


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def test_tree_matches_mujoco(robot):
    rng = np.random.default_rng(3)
    q = rng.uniform(robot.lower, robot.upper, size=(20, robot.n_joints))
    bodies = ["left_wrist_yaw_link", "right_hand_index_1_link", "torso_link", "left_hip_yaw_link"]
    tree = robot.fk(bodies, "tree")
    rot, pos = tree.forward(q)
    data = mujoco.MjData(robot.model)
    base = robot.torso_from_world
    for t in range(len(q)):
        data.qpos[:] = robot.qpos(q[t])
        mujoco.mj_kinematics(robot.model, data)
        for name in bodies:
            b = robot.model.body(name).id
            i = tree.index[name]
            assert np.allclose(pos[t, i], base[:3, :3] @ data.xpos[b] + base[:3, 3], atol=1e-6)
            assert np.allclose(rot[t, i], base[:3, :3] @ data.xmat[b].reshape(3, 3), atol=1e-6)
    # the NumPy link poses agree with the differentiable pytorch-kinematics path
    links = ["left_wrist", "right_elbow", "head"]
    p_np, r_np = robot.link_poses(q, links)
    p_pk, r_pk = robot.link_points(torch.tensor(q), links)
    assert np.allclose(p_np, p_pk.numpy(), atol=1e-6) and np.allclose(r_np, r_pk.numpy(), atol=1e-6)


def test_hull_polytopes_contain_their_geoms(robot):
    px = robot_proxies(robot)
    model, data = robot.model, mujoco.MjData(robot.model)
    data.qpos[:] = robot.qpos(robot.tpose)
    mujoco.mj_kinematics(model, data)
    assert len(px.hull_body) > 0 and len(px.hull_pairs) > 0
    # torso shell: every mesh vertex lies inside (or on) the conservative polytope
    g = [g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body("torso_link").id
         and model.geom_group[g] == 3][0]
    m = model.geom_dataid[g]
    verts = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
    b = model.body("torso_link").id
    world = data.geom_xpos[g] + verts @ data.geom_xmat[g].reshape(3, 3).T
    local = (world - data.xpos[b]) @ data.xmat[b].reshape(3, 3)
    h = [i for i, body in enumerate(px.hull_body) if px.bodies[body] == "torso_link"][0]
    planes = px.hull_planes[h]
    sd = (local @ planes[:, :3].T + planes[:, 3]).max(1)
    assert sd.max() <= 1e-9
    # and it is tight: the farthest vertex touches its hull within a few millimetres
    assert sd.max() > -0.005


def test_contacts_rest_clear_and_planted_overlap(robot):
    q = np.tile(robot.rest, (2, 1))
    q[1, robot.joint_index("left_shoulder_roll_joint")] = -0.3  # upper arm pressed into the torso
    counts = self_collision_contacts(robot, q)
    assert counts[0] == 0 and counts[1] > 0
    pairs = contact_pairs(robot, q)
    assert pairs[("left_shoulder_yaw_link", "torso_link")] == 1
