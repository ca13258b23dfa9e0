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
from embody.motion import Motion
from smplx_fixture import write_smplx


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    path = write_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz", vertices=1200,
                       faces=2000)
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
