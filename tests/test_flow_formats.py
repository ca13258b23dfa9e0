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


def _amass(d: Path, rng) -> list[str]:
    d.mkdir()
    np.savez(d / "a.npz", poses=_poses(rng), trans=np.zeros((T, 3)), betas=np.zeros(16),
             gender="neutral", mocap_frame_rate=30.0)
    return [str(d)]


def _smplh(d: Path, rng) -> list[str]:
    d.mkdir()
    np.savez(d / "h.npz", poses=_poses(rng, 156), trans=np.zeros((T, 3)), betas=np.zeros(16),
             mocap_framerate=60.0)
    return [str(d)]


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


def _signavatars(d: Path, rng) -> list[str]:
    d.mkdir()
    smplx = rng.normal(0, 0.1, (T, 182))
    smplx[:, 179:] = 0
    (d / "clip.pkl").write_bytes(pickle.dumps({"smplx": smplx}))
    return [str(d)]


def _arrays(d: Path, rng) -> list[str]:
    d.mkdir()
    np.save(d / "p.npy", _poses(rng))
    np.savez(d / "q.npz", poses=_poses(rng).reshape(T, 55, 3), fps=24.0)
    return [str(d)]


def _manifest(d: Path, rng) -> list[str]:
    (d / "clips").mkdir(parents=True)
    np.save(d / "clips" / "x.npy", _poses(rng))
    np.savez(d / "clips" / "y.npz", poses=_poses(rng), mocap_frame_rate=30.0)
    (d / "list.csv").write_text('path,text\nclips/x.npy,"=cmd|calc"\nclips/y.npz,hi\n')
    return [str(d / "list.csv")]


FORMATS = {"amass": (_amass, 1), "smplh": (_smplh, 1), "soke": (_soke, 2),
           "signavatars": (_signavatars, 1), "arrays": (_arrays, 2), "manifest": (_manifest, 2)}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return tmp_path_factory.mktemp("formats") / "store"  # shared: the shape fit runs once


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_each_format_runs_through_the_flow(prefect_harness, tmp_path, store, capsys,
                                           monkeypatch, fmt):
    monkeypatch.chdir(tmp_path)
    make, n = FORMATS[fmt]
    args = make(tmp_path / "data", np.random.default_rng(0))
    code = main(["run", *args, "--store", str(store), "--name", fmt, *CHEAP])
    out = capsys.readouterr()
    assert code == 0, out.err
    summary = json.loads(out.out)
    assert (summary["ok"], summary["total"]) == (n, n)
    manifest = json.loads(Path(summary["manifest"]).read_text())
    assert Path(manifest["dataset"]).is_absolute()
    for seq in manifest["sequences"].values():
        assert {"source", "retarget", "metrics"} <= set(seq["steps"])
        assert seq["metrics"]["source"]["frames"] == T
    if fmt == "manifest":  # a formula-like text cell is escaped in the report's table
        table = (Path(summary["report"]) / "sequences.csv").read_text()
        assert ",'=cmd|calc," in table and ",=cmd" not in table


def test_soke_source_key_follows_frame_bytes(prefect_harness, tmp_path, store, capsys,
                                             monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = _soke(tmp_path / "data", np.random.default_rng(1))
    run = ["run", *args, "--store", str(store), "--name", "soke-edit", *CHEAP]
    assert main(run) == 0
    first = json.loads(capsys.readouterr().out)
    frame = tmp_path / "data" / "poses" / "s2" / "002.pkl"
    frame.write_bytes(pickle.dumps(_soke_frame(np.random.default_rng(9))))
    assert main(run) == 0
    second = json.loads(capsys.readouterr().out)
    assert first["computed"]["source"] == 2
    assert second["computed"]["source"] == 1  # only the edited sequence is read again
