"""MannequinBody: torch FK/skinning against mannequin-x's NumPy reference, gradients, conventions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mannequin import Mannequin
from scipy.spatial.transform import Rotation

from embody.body import BodyModel, MannequinBody, hand_mean, load_body_model
from embody.body.rotations import axis_angle_to_matrix
from embody.config.body import BodyConfig

TOL = 1e-5  # metres


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


def _random(seed: int, frames: int = 3):
    rng = np.random.default_rng(seed)
    pose = (rng.normal(size=(frames, 55, 3)) * 0.6).astype(np.float32)
    betas = (rng.normal(size=10) * 1.5).astype(np.float32)
    transl = rng.normal(size=(frames, 3)).astype(np.float32)
    return pose, betas, transl


def _reference(pose, betas, transl, flat_hand_mean=True, hands=None):
    """mannequin-x NumPy: (transforms (T,54,4,4), vertices (T,V,3))."""
    model = Mannequin("wooden", shape=betas, flat_hand_mean=flat_hand_mean)
    t = pose.shape[0]
    params = dict(body_pose=pose[:, 1:22], head_pose=pose[:, 22:25],
                  hand_pose=pose[:, 25:] if hands is None else hands,
                  pelvis_rotation=pose[:, 0], global_translation=transl,
                  shape=np.broadcast_to(betas, (t, 10)))
    return model.joint_transforms(params), model.vertices(params)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_mannequin_x(body, dtype, seed):
    pose, betas, transl = _random(seed)
    ref_t, ref_v = _reference(pose, betas, transl)
    args = [torch.tensor(a, dtype=dtype) for a in (pose, betas, transl)]
    transforms = body.joint_transforms(*args)
    vertices = body.vertices(*args)
    joints = body.joints(*args)
    assert transforms.dtype == vertices.dtype == joints.dtype == dtype
    assert transforms.shape == (3, 54, 4, 4) and vertices.shape == (3, 24256, 3)
    assert np.abs(transforms.numpy() - ref_t).max() < TOL
    assert np.abs(vertices.numpy() - ref_v).max() < TOL
    assert np.abs(joints.numpy() - ref_t[..., :3, 3]).max() < TOL


def test_relative_hands_equal_absolute_plus_mean(body):
    """Our hands are absolute: relative hands h in mannequin-x equal h + hand_mean here."""
    pose, betas, transl = _random(2, frames=2)
    _, ref_v = _reference(pose, betas, transl, flat_hand_mean=False)
    absolute = pose.copy()
    absolute[:, 25:] += body.hand_mean
    ours = body.vertices(torch.tensor(absolute), torch.tensor(betas), torch.tensor(transl))
    assert np.abs(ours.numpy() - ref_v).max() < TOL
    np.testing.assert_array_equal(hand_mean(), body.hand_mean)
    assert body.hand_mean.shape == (30, 3)


def test_joint_names_follow_smplx(body):
    ref = Mannequin("wooden")
    for name, ref_name in [("left_wrist", "L_Wrist"), ("right_shoulder", "R_Shoulder"),
                           ("spine3", "Spine3"), ("left_thumb3", "L_Thumb3"), ("left_hand", "L_Hand")]:
        assert body.joint_index(name) == ref.joint_index(ref_name)
    assert len(body.joint_names) == 54 and body.parents.tolist() == list(ref.parents)
    np.testing.assert_array_equal(body.joint_indices(["left_wrist", "right_wrist"]), [20, 21])
    with pytest.raises(ValueError, match="jaw"):
        body.joint_index("jaw")


def test_joint_gradients_wrt_pose_and_betas(body):
    for scale in (0.0, 0.5):  # 0: the T-pose, where a naive Rodrigues gives NaN gradients
        pose = (torch.randn(2, 55, 3, generator=torch.Generator().manual_seed(3)) * scale)
        pose = pose.double().requires_grad_()
        betas = torch.zeros(10, dtype=torch.float64, requires_grad=True)
        wrists = body.joints(pose, betas)[:, body.joint_indices(["left_wrist", "right_wrist"])]
        wrists.square().sum().backward()
        for grad in (pose.grad, betas.grad):
            assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_betas_gradient_matches_finite_difference(body):
    betas = torch.tensor(np.random.default_rng(4).normal(size=10), requires_grad=True)
    pose = torch.full((1, 55, 3), 0.2, dtype=torch.float64)
    body.joints(pose, betas)[0, body.joint_index("left_wrist"), 1].backward()
    eps = 1e-6
    step = torch.zeros(10, dtype=torch.float64)
    step[0] = eps
    y = lambda b: body.joints(pose, b)[0, body.joint_index("left_wrist"), 1]  # noqa: E731
    fd = (y(betas.detach() + step) - y(betas.detach() - step)) / (2 * eps)
    assert abs(betas.grad[0].item() - fd.item()) < 1e-6


def test_vertex_gradient_wrt_pose(body):
    pose = torch.zeros(1, 55, 3, requires_grad=True)
    body.vertices(pose, torch.zeros(10)).sum().backward()
    assert torch.isfinite(pose.grad).all() and pose.grad.abs().sum() > 0


def test_betas_per_frame_and_rest(body):
    pose, betas, transl = _random(5, frames=2)
    p, b, tr = torch.tensor(pose), torch.tensor(betas), torch.tensor(transl)
    per_frame = body.joints(p, b.expand(2, 10), tr)
    assert torch.allclose(per_frame, body.joints(p, b, tr), atol=1e-6)
    rest = body.rest_vertices(b)
    assert torch.allclose(body.vertices(body.tpose(1), b)[0], rest, atol=1e-6)
    assert torch.allclose(body.joints(body.tpose(1), b)[0], body.rest_joints(b), atol=1e-6)
    shifted = body.vertices(p, b, tr + torch.tensor([0.0, 1.0, 0.0]))
    assert torch.allclose(shifted - body.vertices(p, b, tr), torch.tensor([0.0, 1.0, 0.0]), atol=1e-5)
    with pytest.raises(ValueError, match="per-frame betas"):
        body.vertices(p, torch.randn(2, 10))
    with pytest.raises(ValueError, match="pose must be"):
        body.joints(torch.zeros(2, 54, 3), b)


def test_axis_angle_to_matrix_matches_scipy():
    aa = np.random.default_rng(6).normal(size=(64, 3))
    aa[:4] *= 1e-5  # the series branch
    aa[4] = 0.0
    ours = axis_angle_to_matrix(torch.tensor(aa)).numpy()
    np.testing.assert_allclose(ours, Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)


def test_load_body_model_default_is_cached_mannequin():
    model = load_body_model(BodyConfig())
    assert isinstance(model, BodyModel) and model.name == "mannequin"
    assert load_body_model() is model


def test_repeated_calls_give_identical_bytes(body):
    pose, betas, transl = (torch.tensor(a) for a in _random(7, frames=2))
    first = body.vertices(pose, betas, transl).numpy().tobytes()
    assert body.vertices(pose, betas, transl).numpy().tobytes() == first
