"""`embody retarget IN OUT.npz` on one synthetic motion file."""

import json

import numpy as np
import pytest

from embody.cli import main
from embody.io import save
from embody.motion import Motion
from embody.synth import generate_sequence


@pytest.fixture(scope="module")
def motion_file(tmp_path_factory):
    m = generate_sequence(0, 0)
    short = Motion(pose=m.pose[:24], transl=m.transl[:24], betas=m.betas, fps=m.fps)
    return save(short, tmp_path_factory.mktemp("motion") / "sign.npz")


@pytest.mark.parametrize("robot,n_joints", [("unitree_g1_dex3", 43), ("unitree_h1", 19)])
def test_cli_writes_trajectory(motion_file, tmp_path, capsys, monkeypatch, robot, n_joints):
    monkeypatch.setenv("EMBODY_CACHE", str(tmp_path / "cache"))  # shape-fit cache
    out = tmp_path / "q.npz"
    code = main(["retarget", str(motion_file), str(out), "--robot", robot, "--json",
                 "--set", "ik.iterations=10"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["robot"] == robot and summary["frames"] == 24
    with np.load(out) as z:
        assert z["q"].shape == (24, n_joints)
        assert len(z["joint_names"]) == n_joints
        assert float(z["fps"]) == 30.0 and float(z["dt"]) == pytest.approx(0.02)
        assert z["q_control"].shape == (39, n_joints)  # 23/30 s at 50 Hz → 39 samples
        metrics = json.loads(str(z["metrics"]))
        assert z["q"].dtype == np.float64 and z["q_control"].dtype == np.float64  # as validated
    assert metrics["joint_limit_violations"] == 0
    for key in ("joint_limit_violations", "velocity_violations", "self_collision_frames"):
        assert metrics[key] == 0 and metrics[f"control_{key}"] == 0, key
    assert metrics["wrist_pos_err_mm"] < 150


def test_cli_bad_input(tmp_path, capsys):
    assert main(["retarget", str(tmp_path / "missing.npz"), str(tmp_path / "o.npz")]) == 2
    assert main(["retarget", str(tmp_path / "missing.npz"), str(tmp_path / "o.npz"), "--robot", "nope"]) == 2
    assert "error" in capsys.readouterr().err
