"""`embody collide IN OUT`: a file round trip, presets, config overlays and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from embody.config import configs_dir
from embody.cli import main
from embody.config import load_config
from embody.io import load, save
from embody.motion import JOINT_NAMES, Motion

J = JOINT_NAMES.index


def colliding(frames: int = 6) -> Motion:
    pose = np.zeros((frames, 55, 3))
    pose[:, J("left_shoulder")] = (0.0, -1.0, -0.3)
    pose[:, J("right_shoulder")] = (0.0, 1.0, 0.3)
    pose[:, J("left_elbow"), 1] = np.linspace(-1.8, -2.2, frames)
    pose[:, J("right_elbow"), 1] = np.linspace(1.8, 2.2, frames)
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=30.0,
                  meta={"text": "toy"})


def test_round_trip(tmp_path, capsys):
    src, dst = tmp_path / "in.npz", tmp_path / "out.npz"
    save(colliding(), src)
    assert main(["collide", str(src), str(dst), "--set", "collision.steps=60", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["improved"] and report["energy_after"] < report["energy_before"]
    out = load(dst)
    assert out.num_frames == 6 and out.meta["text"] == "toy"
    assert out.meta["collision"]["energy_after"] == pytest.approx(report["energy_after"])
    frozen = [i for i in range(55) if i < 13 or i in (15, 22, 23, 24)]
    assert np.array_equal(out.pose[:, frozen], load(src).pose[:, frozen])
    assert main(["collide", str(src), str(tmp_path / "h.npz"), "--preset", "hands",
                 "--set", "collision.steps=3"]) == 0
    line = capsys.readouterr().out
    assert "L_col" in line and "->" in line
    assert np.array_equal(load(tmp_path / "h.npz").pose[:, :25], load(src).pose[:, :25])


def test_bad_input_exits_2(tmp_path, capsys):
    assert main(["collide", str(tmp_path / "missing.npz"), str(tmp_path / "o.npz")]) == 2
    src = tmp_path / "in.npz"
    save(colliding(), src)
    assert main(["collide", str(src), str(tmp_path / "o.npz"),
                 "--set", "collision.lr=-1"]) == 2
    assert "collision.lr" in capsys.readouterr().err


def test_paper_overlay():
    cfg = load_config([configs_dir() / "collision/paper.yaml"]).collision
    assert cfg.mask == "hands" and cfg.steps == 500 and cfg.lambda_col == 50.0
    assert cfg.lambda_close == 1e-4 and cfg.lambda_smooth == 1e-4 and cfg.lr == 0.01
    assert cfg.clearance == 0.0
