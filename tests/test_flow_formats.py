"""Every input format through `embody run`: the source step keys and loads each one.

SOKE sequences are folders: their key hashes the frame files, so editing one frame reruns it.
"""

from __future__ import annotations

import gzip
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from embody.cli import main

#: Real steps made cheap: no collision optimisation, no critic, no render, one IK iteration.
CHEAP = ["--critic", "none", "--no-render", "--set", "collision.enabled=false",
         "--set", "ik.iterations=1", "--set", "ik.shape_iterations=10", "--no-progress", "--json"]
T = 4


def _poses(rng, width=165):
    return rng.normal(0, 0.1, (T, width))


def _amass(d: Path, rng) -> None:
    np.savez(d / "amass.npz", poses=_poses(rng), trans=np.zeros((T, 3)), betas=np.zeros(16),
             gender="neutral", mocap_frame_rate=30.0)


def _smplh(d: Path, rng) -> None:
    np.savez(d / "smplh.npz", poses=_poses(rng, 156), trans=np.zeros((T, 3)), betas=np.zeros(16),
             mocap_framerate=60.0)


def _soke_frame(rng) -> dict:
    return {"smplx_root_pose": rng.normal(0, 0.1, 3), "smplx_body_pose": rng.normal(0, 0.1, 63),
            "smplx_lhand_pose": rng.normal(0, 0.1, 45), "smplx_rhand_pose": rng.normal(0, 0.1, 45),
            "smplx_jaw_pose": np.zeros(3), "smplx_shape": np.zeros(10),
            "cam_trans": np.array([0.0, 0.0, 2.0])}


def _soke(d: Path, rng) -> list[str]:
    for name in ("s1", "s2"):
        seq = d / "poses" / name
        seq.mkdir(parents=True)
        for i in range(T):
            (seq / f"{i:03d}.pkl").write_bytes(pickle.dumps(_soke_frame(rng)))
    split = [{"name": "s1", "text": "hello"}, {"name": "s2", "text": "thanks"}]
    (d / "csl_clean.train").write_bytes(gzip.compress(pickle.dumps(split)))
    return [str(d), "--split", "train"]


def _signavatars(d: Path, rng) -> None:
    smplx = rng.normal(0, 0.1, (T, 182))
    smplx[:, 179:] = 0
    (d / "signavatars.pkl").write_bytes(pickle.dumps({"smplx": smplx}))


def _arrays(d: Path, rng) -> None:
    np.save(d / "plain.npy", _poses(rng).reshape(T, 55, 3))


def _run(args: list[str], store: Path, name: str, capsys) -> dict:
    code = main(["run", *args, "--store", str(store), "--name", name, *CHEAP])
    out = capsys.readouterr()
    assert code == 0, out.err
    summary = json.loads(out.out)
    assert summary["ok"] == summary["total"]
    manifest = json.loads(Path(summary["manifest"]).read_text())
    assert Path(manifest["dataset"]).is_absolute()
    for seq in manifest["sequences"].values():
        assert {"source", "collide", "retarget", "metrics"} <= set(seq["steps"])
        assert seq["metrics"]["source"]["frames"] == T
    return summary


def test_every_file_format_runs_through_the_flow(prefect_harness, tmp_path, capsys,
                                                 monkeypatch):
    """One CSV manifest lists a file of each format (SOKE roots: the next test)."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    data = tmp_path / "data"
    (data / "clips").mkdir(parents=True)
    for make in (_amass, _smplh, _signavatars, _arrays):
        make(data / "clips", rng)
    files = sorted(p.name for p in (data / "clips").iterdir())
    rows = [f"clips/{f},\"=cmd|{f}\"" for f in files]
    (data / "list.csv").write_text("path,text\n" + "\n".join(rows) + "\n")
    summary = _run([str(data / "list.csv")], tmp_path / "store", "formats", capsys)
    assert summary["total"] == 4
    fps = {sid: seq["metrics"]["source"]["fps"] for sid, seq in
           json.loads(Path(summary["manifest"]).read_text())["sequences"].items()}
    assert fps["clips/smplh"] == 60.0 and fps["clips/plain"] == 30.0
    # formula-like text cells are escaped in the report's per-sequence table
    table = (Path(summary["report"]) / "sequences.csv").read_text()
    assert ",'=cmd|smplh.npz," in table and ",=cmd" not in table


def test_soke_root_runs_and_its_key_follows_frame_bytes(prefect_harness, tmp_path, capsys,
                                                        monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = [str(tmp_path / "data"), "--split", "train"]
    _soke(tmp_path / "data", np.random.default_rng(1))
    first = _run(args, tmp_path / "store", "soke", capsys)
    frame = tmp_path / "data" / "poses" / "s2" / "002.pkl"
    frame.write_bytes(pickle.dumps(_soke_frame(np.random.default_rng(9))))
    second = _run(args, tmp_path / "store", "soke", capsys)
    assert first["total"] == 2 and first["computed"]["source"] == 2
    assert second["computed"]["source"] == 1  # only the edited sequence is read again
