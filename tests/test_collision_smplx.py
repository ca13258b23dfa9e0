"""The same collision code path on the SMPL-X backend (a small random SMPL-X-format file)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_collision_energy import reference_energies

from embody.body import load_body_model
from embody.collision import collision_model, frame_energies, mitigate, part_volumes
from embody.config.body import BodyConfig
from embody.config.collision import CollisionConfig
from embody.motion import JOINT_NAMES, PARENTS, Motion


def write_smplx(path, seed: int = 0):
    """A fake SMPL-X npz (random values, real keys and shapes), as tests/test_body_smplx.py."""
    rng = np.random.default_rng(seed)
    v = 1200
    weights = rng.random((v, 55)) ** 8
    weights /= weights.sum(1, keepdims=True)
    regressor = rng.random((55, v))
    regressor /= regressor.sum(1, keepdims=True)
    kintree = np.stack([PARENTS, np.arange(55)]).astype(np.int64)
    kintree[0, 0] = 4294967295
    np.savez(path, v_template=rng.normal(size=(v, 3)) * 0.3, f=rng.integers(0, v, (2000, 3)),
             weights=weights, shapedirs=rng.normal(size=(v, 3, 400)) * 0.01,
             posedirs=rng.normal(size=(v, 3, 486)) * 1e-3, J_regressor=regressor,
             kintree_table=kintree, hands_meanl=rng.normal(size=45) * 0.2,
             hands_meanr=rng.normal(size=45) * 0.2,
             joint2num=np.array({n: i for i, n in enumerate(JOINT_NAMES)}, dtype=object))
    return path


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    path = write_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz")
    return load_body_model(BodyConfig(backend="smplx", model_path=str(path)))


def test_energy_matches_reference_on_smplx(body):
    vols = part_volumes(body)
    assert len(vols.part_names) > 20 and np.isnan(vols.overfill).all()  # toy mesh: not closed
    rng = np.random.default_rng(0)
    pose = rng.normal(0, 0.3, (3, 55, 3))
    model = collision_model(body, vertex_stride=2)
    ours = frame_energies(model, body.joint_transforms(
        torch.as_tensor(pose), torch.zeros(10, dtype=torch.float64))).numpy()
    np.testing.assert_allclose(ours, reference_energies(body, pose, 2), rtol=1e-9, atol=1e-12)
    assert (ours > 0).all()


def test_mitigate_on_smplx(body):
    pose = np.random.default_rng(1).normal(0, 0.3, (4, 55, 3))
    motion = Motion(pose=pose, transl=np.zeros((4, 3)), betas=np.zeros(10), fps=30.0)
    r = mitigate(motion, body, CollisionConfig(mask="hands_wrists", steps=10, vertex_stride=2))
    assert r.metrics["energy_after"] < r.metrics["energy_before"]
    assert np.array_equal(r.motion.pose[:, :20], motion.pose[:, :20])
