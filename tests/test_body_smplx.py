"""SMPLXBody on a small SMPL-X-format file the test builds (random values, right keys and shapes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from body_models.smplx.numpy import SMPLX as NumpySMPLX

from embody.body import SMPLXBody, load_body_model
from embody.body.parts import dominant_parts
from embody.config.body import BodyConfig
from embody.errors import ConfigError, InputError
from smplx_fixture import write_smplx

NUM_VERTICES = 400


@pytest.fixture(scope="module")
def model_file(tmp_path_factory) -> Path:
    return write_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz")


@pytest.fixture(scope="module")
def body(model_file) -> SMPLXBody:
    return load_body_model(BodyConfig(backend="smplx", model_path=str(model_file)))


def test_loader_and_shapes(body, model_file):
    assert isinstance(body, SMPLXBody) and body.name == "smplx"
    assert load_body_model(BodyConfig(backend="smplx", model_path=str(model_file))) is body
    pose = torch.randn(3, 55, 3, dtype=torch.float64) * 0.3
    betas = torch.randn(10, dtype=torch.float64)
    assert body.joints(pose, betas).shape == (3, 55, 3)
    assert body.joint_transforms(pose, betas).shape == (3, 55, 4, 4)
    vertices = body.vertices(pose, betas)
    assert vertices.shape == (3, NUM_VERTICES, 3) and vertices.dtype == torch.float64
    assert body.vertices(pose.float(), betas.float()).dtype == torch.float32
    assert body.faces.shape == (600, 3) and body.skin_weights.shape == (NUM_VERTICES, 55)
    assert body.joint_index("left_wrist") == 20 and body.joint_index("jaw") == 22


def test_rest_shape_is_the_linear_blend(body, model_file):
    data = np.load(model_file, allow_pickle=True)
    betas = np.random.default_rng(1).normal(size=10)
    rest = data["v_template"] + data["shapedirs"][:, :, :10] @ betas
    ours = body.rest_vertices(torch.tensor(betas)).numpy()
    np.testing.assert_allclose(ours, rest, atol=1e-5)
    np.testing.assert_allclose(body.rest_joints(torch.tensor(betas)).numpy(),
                               data["J_regressor"] @ rest, atol=1e-5)


def test_pelvis_rotation_and_translation(body):
    betas = torch.zeros(10, dtype=torch.float64)
    pose = torch.zeros(2, 55, 3, dtype=torch.float64)
    pose[:, 0] = torch.tensor([0.3, -1.0, 0.5])
    transl = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    joints = body.joints(pose, betas, transl)
    rest = body.rest_joints(betas)
    assert torch.allclose(joints[:, 0], rest[0] + transl, atol=1e-6)  # root orient is about the pelvis
    assert torch.allclose(joints[1] - joints[0], transl[1].expand(55, 3), atol=1e-6)


def test_hands_are_absolute(body, model_file):
    """Relative hands h in body-models' default model equal h + hand_mean here."""
    rng = np.random.default_rng(2)
    pose = rng.normal(size=(2, 55, 3)) * 0.3
    betas = rng.normal(size=10)
    reference = NumpySMPLX(model_path=model_file).forward_vertices(
        body_pose=pose[:, 1:22], head_pose=pose[:, 22:25], hand_pose=pose[:, 25:],
        pelvis_rotation=pose[:, 0], shape=np.broadcast_to(betas, (2, 10)), expression=np.zeros((2, 10)))
    absolute = pose.copy()
    absolute[:, 25:] += body.hand_mean
    ours = body.vertices(torch.tensor(absolute), torch.tensor(betas)).numpy()
    np.testing.assert_allclose(ours, reference, atol=1e-5)


def test_gradients(body):
    pose = torch.zeros(2, 55, 3, dtype=torch.float64, requires_grad=True)
    betas = torch.zeros(10, dtype=torch.float64, requires_grad=True)
    body.joints(pose, betas)[:, [20, 21]].square().sum().backward()
    for grad in (pose.grad, betas.grad):
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_parts_and_hulls(body):
    expected = dominant_parts(body.skin_weights, body.joint_names)
    np.testing.assert_array_equal(body.vertex_parts, expected.vertex_parts)
    betas = np.random.default_rng(3).normal(size=10)
    rest = body.rest_vertices(torch.tensor(betas)).numpy()
    bind = body.rest_joints(torch.tensor(betas)).numpy()
    for piece in body.collision_geometry(betas):
        local = rest[body.vertex_parts == piece.part] - bind[piece.joint]
        assert (local @ piece.planes[:, :3].T + piece.planes[:, 3]).max() <= 1e-6


def test_missing_file_names_the_path(tmp_path):
    missing = tmp_path / "nowhere" / "SMPLX_NEUTRAL.npz"
    with pytest.raises(InputError, match="not found") as err:
        SMPLXBody(missing)
    assert err.value.path == str(missing) and str(missing) in str(err.value)


def test_folder_picks_gender_file(tmp_path):
    write_smplx(tmp_path / "SMPLX_FEMALE.npz", seed=4)
    body = SMPLXBody.from_config(BodyConfig(backend="smplx", model_path=str(tmp_path), gender="female"))
    assert body.path == tmp_path / "SMPLX_FEMALE.npz"
    with pytest.raises(InputError) as err:
        SMPLXBody.from_config(BodyConfig(backend="smplx", model_path=str(tmp_path), gender="male"))
    assert err.value.path == str(tmp_path / "SMPLX_MALE.npz")


@pytest.mark.parametrize("key", ["weights", "J_regressor", "hands_meanr"])
def test_missing_key_names_the_field(tmp_path, key):
    path = write_smplx(tmp_path / "SMPLX_NEUTRAL.npz", drop=key)
    with pytest.raises(InputError) as err:
        SMPLXBody(path)
    assert (err.value.path, err.value.field) == (str(path), key)


def test_unreadable_and_misshapen_files(tmp_path):
    garbage = tmp_path / "SMPLX_NEUTRAL.npz"
    garbage.write_bytes(b"not a zip archive")
    with pytest.raises(InputError, match="cannot read"):
        SMPLXBody(garbage)
    with pytest.raises(InputError, match="is a folder"):
        SMPLXBody(tmp_path)
    txt = tmp_path / "model.txt"
    txt.write_text("x")
    with pytest.raises(InputError, match=r"\.npz or \.pkl"):
        SMPLXBody(txt)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{k: v for k, v in np.load(write_smplx(tmp_path / "ok.npz"), allow_pickle=True).items()
                     if k != "shapedirs"}, shapedirs=np.zeros((NUM_VERTICES, 3, 20)))
    with pytest.raises(InputError) as err:
        SMPLXBody(bad)
    assert err.value.field == "shapedirs"


def test_smplx_backend_needs_a_model_path():
    with pytest.raises(ConfigError) as err:
        load_body_model(BodyConfig(backend="smplx"))
    assert err.value.key == "body.model_path"
