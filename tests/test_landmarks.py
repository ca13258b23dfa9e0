"""Landmarks on both bodies (mannequin, SMPL-X) and both robots (G1 Dex3, H1) lie on their surfaces."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull

from embody.body import load_body_model
from embody.body.landmarks import BODY_LANDMARKS, CARRIED_BY, LANDMARKS, landmark_positions
from embody.config.body import BodyConfig
from embody.config.robot import RobotConfig
from embody.robot import load_robot
from embody.robot.contacts import subtree_ids
from smplx_fixture import write_smplx


@pytest.fixture(scope="module")
def mannequin():
    return load_body_model(BodyConfig())


@pytest.fixture(scope="module")
def smplx_body(tmp_path_factory):
    path = write_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz")
    return load_body_model(BodyConfig(backend="smplx", model_path=str(path)))


@pytest.mark.parametrize("which", ["mannequin", "smplx_body"])
def test_body_landmarks_on_the_mesh(which, request):
    body = request.getfixturevalue(which)
    betas = np.random.default_rng(0).normal(size=10) * 0.5
    pose = np.zeros((1, 55, 3))
    points, normals, lm = landmark_positions(body, pose, betas)
    assert lm.names == LANDMARKS and points.shape == (1, len(LANDMARKS), 3)
    verts = body.vertices(torch.as_tensor(pose), torch.as_tensor(betas))[0].numpy()
    dist = np.linalg.norm(verts[None] - points[0][:, None], axis=-1).min(1)
    assert dist.max() < 2e-3, dict(zip(lm.names, dist))
    np.testing.assert_allclose(normals[0], [[0, -1, 0], [0, -1, 0]], atol=1e-6)  # palms down
    assert lm.scale > 0


@pytest.mark.parametrize("which", ["mannequin", "smplx_body"])
def test_landmark_positions_equal_the_dense_blend_bit_for_bit(which, request):
    """`LandmarkSet.positions` sums only the joints that skin each landmark: the same bits as
    the dense blend over every joint (the pipeline's digests rely on it)."""
    from embody.body.landmarks import body_landmarks
    body = request.getfixturevalue(which)
    rng = np.random.default_rng(4)
    betas = rng.normal(size=10) * 0.5
    lm = body_landmarks(body, betas)
    assert (np.count_nonzero(lm.weight, axis=1) > 1).any() or which == "mannequin"
    with torch.no_grad():
        t = body.joint_transforms(torch.as_tensor(rng.normal(size=(40, 55, 3)) * 0.4),
                                  torch.as_tensor(betas), torch.as_tensor(rng.normal(size=(40, 3)))).numpy()
    points, normals = lm.positions(t)
    per_joint = t[:, None, :, :3, 3] + np.einsum("tjab,kjb->tkja", t[..., :3, :3], lm.offset)
    assert np.array_equal(points, np.einsum("tkja,kj->tka", per_joint, lm.weight))
    assert np.array_equal(normals, np.einsum("tkab,kb->tka", t[:, lm.normal_joint][..., :3, :3],
                                             lm.normal_local))
    assert lm.positions(t[:0])[0].shape == (0, len(lm.names), 3)


def test_mannequin_landmarks_follow_the_pose_and_read_right(mannequin):
    rng = np.random.default_rng(1)
    pose = rng.normal(size=(3, 55, 3)) * 0.3
    points, _, lm = landmark_positions(mannequin, pose, np.zeros(10))
    verts = mannequin.vertices(torch.as_tensor(pose), torch.zeros(10, dtype=torch.float64)).numpy()
    moved = np.linalg.norm(verts[:, lm.vertex] - points, axis=-1)
    own = [i for i, n in enumerate(lm.names) if n not in CARRIED_BY]
    assert moved[:, own].max() < 0.01  # rigid shells: the vertex follows its dominant joint
    # a shoulder rides on its collar (the trunk), not on the arm its vertex is skinned to
    joints = mannequin.joints(torch.as_tensor(pose), torch.zeros(10, dtype=torch.float64)).numpy()
    zero = np.zeros((1, 55, 3))
    rest_j = mannequin.joints(torch.as_tensor(zero), torch.zeros(10, dtype=torch.float64)).numpy()
    rest_p, _, _ = landmark_positions(mannequin, zero, np.zeros(10))
    for name, carrier in CARRIED_BY.items():
        i, j = lm.names.index(name), mannequin.joint_index(carrier)
        np.testing.assert_allclose(np.linalg.norm(points[:, i] - joints[:, j], axis=-1),
                                   np.linalg.norm(rest_p[0, i] - rest_j[0, j]), atol=1e-9)
        assert moved[:, i].max() > 0.01  # its arm-skinned vertex does move away
    rest, _, _ = landmark_positions(mannequin, np.zeros((1, 55, 3)), np.zeros(10))
    p = dict(zip(lm.names, rest[0]))
    assert p["head_top"][1] > p["forehead"][1] > p["left_eye"][1] > p["nose"][1] > p["chin"][1]
    assert p["chin"][1] > p["throat"][1] > p["sternum"][1] > p["belly"][1] > p["left_hip"][1]
    assert p["left_shoulder"][0] > 0.1 > -0.1 > p["right_shoulder"][0]
    assert p["nose"][2] > p["throat"][2]  # face to the front
    for s in ("left", "right"):
        reach = [np.linalg.norm(p[f"{s}_{f}_tip"] - p[f"{s}_wrist"]) for f in ("index", "middle")]
        assert min(reach) > np.linalg.norm(p[f"{s}_palm"] - p[f"{s}_wrist"]) + 0.05


def _surface_distance(model, data, geoms, point):
    best = np.inf
    for g in geoms:
        pos, rot = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            v = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
            w = v @ rot.T + pos
            best = min(best, np.linalg.norm(w - point, axis=1).min())
            if model.geom_contype[g] or model.geom_conaffinity[g]:  # MuJoCo collides its convex hull
                eq = ConvexHull(w).equations
                best = min(best, abs((eq[:, :3] @ point + eq[:, 3]).max()))
        elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
            best = min(best, abs(np.linalg.norm(point - pos) - model.geom_size[g][0]))
    return best


@pytest.mark.parametrize("name", ["unitree_g1_dex3", "unitree_h1"])
def test_robot_landmarks_on_the_geometry(name):
    robot = load_robot(RobotConfig(name=name))
    spec = robot.spec.landmarks
    assert set(BODY_LANDMARKS) <= set(spec)
    fingers = {"unitree_g1_dex3": ("thumb", "index", "middle"), "unitree_h1": ()}[name]
    for s in ("left", "right"):
        assert {f"{s}_wrist", f"{s}_palm"} | {f"{s}_{f}_tip" for f in fingers} <= set(spec)
    m = robot.model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.qpos(robot.tpose)
    mujoco.mj_kinematics(m, d)
    points, normals, names = robot.landmark_points(robot.tpose[None])
    world = np.linalg.inv(robot.torso_from_world)
    for k, lname in enumerate(names):
        p = world[:3, :3] @ points[0, k] + world[:3, 3]
        b = m.body(spec[lname].body).id
        # a shoulder is carried by the torso (as the body's by its collar) but lies on the arm's top
        bodies = subtree_ids(m, spec[lname].body) if lname in CARRIED_BY else {b}
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies]
        assert _surface_distance(m, d, geoms, p) < 3e-3, lname
    np.testing.assert_allclose(normals[0], [[0, 0, -1], [0, 0, -1]], atol=1e-3)  # palms down
    p = dict(zip(names, points[0]))
    assert p["head_top"][2] > p["nose"][2] > p["chin"][2] > p["sternum"][2] > p["belly"][2]
    assert p["chin"][0] > 0.02 and p["left_shoulder"][1] > 0.05 > -0.05 > p["right_shoulder"][1]
    assert 0.15 < robot.body_scale < 0.5
