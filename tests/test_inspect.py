"""`embody inspect`: what a file holds, text and JSON, for field formats and synth files."""

from __future__ import annotations

import json
import pickle

import numpy as np

from embody.cli import main
from embody.io import save
from embody.motion import Motion, MotionSource


def _synthish(path):
    pose = np.zeros((30, 55, 3), np.float32)
    pose[:, 17] = [0.0, 0.0, np.pi / 2]  # right shoulder at 90°
    pose[:, 40:55, 2] = np.linspace(0, 1, 30)[:, None]  # right fingers curl up to 1 rad
    meta = {"text": "HELLO YOU", "gloss": ["HELLO", "YOU"],
            "artifacts": [{"kind": "hand_face", "start": 3, "end": 9, "wrist_depth_m": 0.03}]}
    save(Motion(pose=pose, transl=np.zeros((30, 3)), betas=np.zeros(10), fps=30.0,
                source=MotionSource("", "synth", "absolute"), meta=meta), path)


def test_inspect_text_output(tmp_path, capsys):
    _synthish(tmp_path / "s.npz")
    assert main(["inspect", str(tmp_path / "s.npz")]) == 0
    out = capsys.readouterr().out
    assert "format           embody" in out
    assert "30 @ 30 fps (1.00 s)" in out
    assert "HELLO YOU" in out and "hand_face [3, 9) wrist_depth_m=0.03" in out
    line = next(line for line in out.splitlines() if line.strip().startswith("right_arm"))
    assert line.split()[-1] == "90.0"


def test_inspect_json_joint_ranges(tmp_path, capsys):
    _synthish(tmp_path / "s.npz")
    assert main(["inspect", str(tmp_path / "s.npz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 30 and info["fps"] == 30.0 and info["duration_s"] == 1.0
    assert info["hand_convention"] == "absolute"
    assert info["joint_ranges"]["right_arm"] == {"min_deg": 0.0, "max_deg": 90.0}
    assert info["joint_ranges"]["right_hand"]["max_deg"] == round(float(np.degrees(1.0)), 2)
    assert info["joint_ranges"]["left_hand"] == {"min_deg": 0.0, "max_deg": 0.0}
    assert info["artifacts"][0]["kind"] == "hand_face" and info["gloss"] == ["HELLO", "YOU"]


def test_inspect_relative_source(tmp_path, capsys):
    (tmp_path / "s.pkl").write_bytes(pickle.dumps({"smplx": np.zeros((4, 182))}))
    assert main(["inspect", str(tmp_path / "s.pkl"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "signavatars" and info["hand_convention"] == "relative"
    # zero relative hands are the relaxed mean: non-zero once absolute
    assert info["joint_ranges"]["left_hand"]["max_deg"] > 10


def test_inspect_fps_for_formats_without_one(tmp_path, capsys):
    np.save(tmp_path / "p.npy", np.zeros((50, 165), np.float32))
    assert main(["inspect", str(tmp_path / "p.npy"), "--fps", "25", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["fps"] == 25.0 and info["duration_s"] == 2.0
    assert main(["inspect", str(tmp_path / "p.npy"), "--fps", "0"]) == 2


def test_inspect_dataset_lists_sequences(tmp_path, capsys):
    _synthish(tmp_path / "b.npz")
    _synthish(tmp_path / "sub" / "a.npz")
    assert main(["inspect", str(tmp_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "folder" and info["ids"] == ["b", "sub/a"] and info["sequences"] == 2
    assert main(["inspect", str(tmp_path), "--split", "train"]) == 2  # not a SOKE root
    assert "split" in capsys.readouterr().err
