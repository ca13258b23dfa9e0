"""Shape fit (Eq. 4): residuals, the value of the global scale, and the two-level cache."""

import importlib

import numpy as np
import pytest

from embody.body import load_body_model
from embody.config.ik import IKConfig
from embody.robot import load_robot

# The package re-exports the function `shape_fit`, which shadows the module attribute.
sf = importlib.import_module("embody.retarget.shape_fit")


@pytest.fixture(scope="module")
def robot():
    return load_robot()


@pytest.fixture(scope="module")
def body():
    return load_body_model()


def test_residuals_reasonable_and_scale_helps(robot, body):
    with_scale = sf.fit(robot, body, IKConfig())
    without = sf.fit(robot, body, IKConfig(shape_fit_scale=False))
    res = dict(zip(with_scale.joint_names, with_scale.residual_mm))
    assert res["left_wrist"] < 30 and res["right_wrist"] < 30
    assert res["left_elbow"] < 50 and res["right_elbow"] < 50
    assert with_scale.mean_residual_mm < 60
    assert 0.6 < with_scale.scale < 0.9  # G1 is smaller than the average human
    assert without.scale == 1.0
    assert with_scale.mean_residual_mm < without.mean_residual_mm
    assert np.all(np.isfinite(with_scale.betas)) and with_scale.betas.shape == (10,)


def test_cached_in_memory_and_on_disk(robot, body, tmp_path, monkeypatch):
    monkeypatch.setenv("EMBODY_CACHE", str(tmp_path))
    monkeypatch.setattr(sf, "_MEMORY", {})
    cfg = IKConfig(shape_iterations=50)
    first = sf.shape_fit(robot, body, cfg)
    assert sf.shape_fit(robot, body, cfg) is first
    files = list((tmp_path / "shape_fit").glob("*.npz"))
    assert len(files) == 1
    monkeypatch.setattr(sf, "_MEMORY", {})
    loaded = sf.shape_fit(robot, body, cfg)
    assert loaded is not first
    assert np.array_equal(loaded.betas, first.betas) and loaded.scale == first.scale
    assert np.array_equal(loaded.residual_mm, first.residual_mm)
    other = sf.shape_fit(robot, body, IKConfig(shape_iterations=60))  # other settings: other entry
    assert len(list((tmp_path / "shape_fit").glob("*.npz"))) == 2 and other is not loaded
    back = sf.ShapeFit.from_arrays(first.to_arrays(), first.to_attrs())
    assert np.array_equal(back.offset, first.offset) and back.joint_names == first.joint_names
