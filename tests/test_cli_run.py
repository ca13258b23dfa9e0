"""`embody run` / `embody serve` end to end: the real chain on tiny sequences, exit codes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from embody.cli import main
from embody.store import ArtifactStore

#: The real steps, made cheap: no collision optimisation, one IK iteration, a short shape fit.
CHEAP = ["--set", "collision.enabled=false", "--set", "ik.iterations=1",
         "--set", "ik.shape_iterations=10", "--set", "critic.rounds=1",
         "--set", "render.width=64", "--set", "render.height=48", "--set", "render.keyframes=2",
         "--set", "render.preview_format=gif", "--set", "render.preview_max_frames=2"]


def _write(folder: Path, n: int = 2, frames: int = 4) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(1)
    for i in range(n):
        np.savez(folder / f"seq{i:03d}.npz", poses=rng.normal(0, 0.1, (frames, 165)),
                 trans=np.zeros((frames, 3)), betas=np.zeros(10), gender="neutral",
                 mocap_frame_rate=30.0)
    return folder


def test_bad_input_exits_2_before_prefect_starts(tmp_path, capsys):
    store = ["--store", str(tmp_path / "s")]
    assert main(["run", str(tmp_path / "missing"), *store]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--workers", "0", *store]) == 2
    assert "run.workers" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--set", "run.bogus=1", *store]) == 2
    assert main(["run", "--runner", "cluster", *store]) == 2


def test_serve_needs_a_reachable_server(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    assert main(["serve", "--cron", "0 3 * * *", "--store", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "PREFECT_API_URL is not set" in err and "prefect server start" in err
    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:9/api")  # discard port: refused
    assert main(["serve", "--cron", "0 3 * * *", "--store", str(tmp_path)]) == 2
    assert "no Prefect server reachable" in capsys.readouterr().err
    assert main(["serve", "--cron", "not a cron", "--store", str(tmp_path)]) == 2


def test_run_isolates_a_failure_then_resumes(prefect_harness, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the report goes to ./reports/<run>
    data = _write(tmp_path / "data")
    args = ["run", str(data), "--store", str(tmp_path / "store"), "--name", "cli", *CHEAP]
    code = main([*args, "--set", "debug.fail_on=[seq001]", "--json", "--no-progress"])
    out = capsys.readouterr()
    assert code == 1, out.err
    summary = json.loads(out.out)
    assert (summary["ok"], summary["failed"]) == (1, 1)
    assert "seq001" in out.err and "InjectedFailure" in out.err  # the failure table
    assert summary["computed"] == {"source": 2, "shape_fit": 1, "collide": 1, "retarget": 1,
                                   "refine": 1, "render": 1, "metrics": 1, "physics": 1}

    code = main([*args, "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    summary = json.loads(out.out)
    assert summary["failed"] == 0
    assert summary["computed"] == {"source": 0, "shape_fit": 0, "collide": 1, "retarget": 1,
                                   "refine": 1, "render": 1, "metrics": 1, "physics": 1}
    store_ = ArtifactStore(tmp_path / "store")
    render = store_.read("render", summary_key(store_, "seq000", "render"))
    assert bytes(render.arrays["sheet_png"][:8]) == b"\x89PNG\r\n\x1a\n"
    assert bytes(render.arrays["preview"][:6]) in (b"GIF89a", b"GIF87a")
    # the two workers computed in processes of their own (`embody.tasks.workers`), forked
    # from a zygote that never rendered: EGL works there
    pids = {r["pid"] for r in store_.computations() if r["step"] != "shape_fit"}
    assert os.getpid() not in pids and 1 <= len(pids) <= 4
    assert "retarget" in out.err  # progress lines on stderr
    store = ArtifactStore(tmp_path / "store")
    q = store.read("retarget", summary_key(store, "seq000", "retarget")).arrays["q"]
    assert q.shape[0] == 4 and np.isfinite(q).all()
    assert main(["store", "verify", "--store", str(tmp_path / "store")]) == 0
    assert main(["store", "ls", "--store", str(tmp_path / "store")]) == 0
    assert "run cli: 2/2 ok" in capsys.readouterr().out


def summary_key(store: ArtifactStore, seq: str, step: str) -> str:
    manifest = json.loads((store.runs_dir / "cli" / "manifest.json").read_text())
    return manifest["sequences"][seq]["steps"][step]
