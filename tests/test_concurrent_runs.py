"""Several drivers of one run name: their manifests merge (store.writers), nothing is lost.

The end-to-end test runs 3 `embody run` processes at once over overlapping windows of one
dataset (`run.offset` + `--limit`) with the same `--name` and store; the manifest must hold
the union, each sequence once and finished, and `embody store verify` must pass.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from embody.cli import main
from embody.store import ArtifactStore, Manifest
from embody.store.writers import locked
from s3_server import s3_endpoint, s3_url, store_root  # noqa: F401 (fixtures)

K = "ab" * 32
#: `embody ...` in a subprocess, with this interpreter.
EMBODY = [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())"]


def _finish(m: Manifest, ids: list[str], status: str = "ok") -> None:
    for sid in ids:
        m.update({"id": sid, "keys": {"source": K}, "metrics": {"source": {"frames": 4}},
                  "status": status, "error": None if status == "ok" else "boom",
                  "failed_step": None if status == "ok" else "collide"})
        m.finish_sequence(sid)


def test_two_writers_merge_and_finish_only_when_both_are_done(store_root):
    store = ArtifactStore(store_root)
    a, b = Manifest(store, "r"), Manifest(store, "r")
    a.start(["s1", "s2", "s3"], dataset="d")
    b.start(["s3", "s4"], dataset="d")  # s3 overlaps
    _finish(b, ["s3", "s4"])
    b.save()
    a.save()  # a's s3 is still pending: b finished it after a started, so b's entry stays
    disk = Manifest.load(store, "r")
    assert sorted(disk.sequences) == ["s1", "s2", "s3", "s4"]
    assert disk.sequences["s3"]["status"] == "ok" and disk.sequences["s1"]["status"] == "pending"
    _finish(a, ["s1", "s2", "s3"])
    a.save(finished=True)
    disk = Manifest.load(store, "r")
    assert disk.data["finished"] is None  # b (same live process) has not finished
    assert [s["status"] for s in disk.sequences.values()] == ["ok"] * 4
    b.save(finished=True)
    disk = Manifest.load(store, "r")
    assert disk.data["finished"] is not None and disk.data["writers"] == {}
    assert disk.keys() == {("source", K)}


def test_a_rerun_restarts_its_own_sequences_and_keeps_the_others(store_root):
    store = ArtifactStore(store_root)
    first = Manifest(store, "r")
    first.start(["s1", "s2"])
    _finish(first, ["s1", "s2"])
    first.save(finished=True)
    again = Manifest(store, "r")
    again.start(["s2", "s3"])  # a later run over s2, s3: s2 starts over, s1 is kept
    disk = Manifest.load(store, "r")
    assert {k: v["status"] for k, v in disk.sequences.items()} == {
        "s1": "ok", "s2": "pending", "s3": "pending"}
    assert disk.data["finished"] is None


def test_a_killed_writer_neither_holds_the_lock_nor_keeps_the_run_unfinished(tmp_path):
    store = ArtifactStore(tmp_path)
    code = ("import sys, time, os; sys.path.insert(0, os.getcwd());"
            "from store import ArtifactStore, Manifest; from store.writers import locked;"
            f"m = Manifest(ArtifactStore({str(tmp_path)!r}), 'r'); m.start(['dead1']);"
            "cm = locked(m.path.parent); cm.__enter__(); print('locked', flush=True);"
            "time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[1])
    assert proc.stdout.readline().strip() == "locked"
    run_dir = store.runs_dir / "r"
    try:
        with locked(run_dir, timeout_s=0.3):
            raise AssertionError("the lock of a live holder was taken")
    except TimeoutError:
        pass
    proc.kill()  # SIGKILL: no cleanup runs; the kernel drops the flock
    proc.wait()
    t0 = time.monotonic()
    with locked(run_dir, timeout_s=5):
        pass
    assert time.monotonic() - t0 < 2
    m = Manifest(store, "r")
    m.start(["s1"])
    _finish(m, ["s1"])
    m.save(finished=True)
    disk = Manifest.load(store, "r")
    assert disk.data["finished"] is not None  # the dead writer does not count as live
    assert disk.sequences["dead1"]["status"] == "pending" and disk.sequences["s1"]["status"] == "ok"


def _write(folder: Path, n: int, frames: int = 4) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(3)
    for i in range(n):
        np.savez(folder / f"seq{i:03d}.npz", poses=rng.normal(0, 0.1, (frames, 165)),
                 trans=np.zeros((frames, 3)), betas=np.zeros(10), gender="neutral",
                 mocap_frame_rate=30.0)
    return folder


@pytest.mark.parametrize("store_root", ["local", "s3"], indirect=True)
def test_three_concurrent_runs_of_one_name_lose_no_sequence(prefect_harness, tmp_path,
                                                           store_root, capsys, monkeypatch):
    data = _write(tmp_path / "data", 8)
    store = store_root
    env = dict(os.environ, EMBODY_WORK_DIR=str(tmp_path / "work"), PREFECT_API_URL=prefect_harness,
               PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    cheap = ["--critic", "none", "--no-render", "--workers", "1", "--batch-size", "1",
             "--set", "collision.enabled=false", "--set", "ik.iterations=1",
             "--set", "ik.shape_iterations=10", "--set", "run.report=false"]
    windows = [(0, 4), (2, 4), (4, 4)]  # seq000-003, seq002-005, seq004-007
    procs = [subprocess.Popen(
        [*EMBODY, "run", str(data), "--store", store,
         "--name", "shared", "--limit", str(limit), "--set", f"run.offset={offset}",
         "--json", "--no-progress", *cheap],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for offset, limit in windows]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-2000:]
        assert json.loads(out)["ok"] == 4
    doc = Manifest.load(ArtifactStore(store), "shared").data
    assert sorted(doc["sequences"]) == [f"seq{i:03d}" for i in range(8)]
    assert {s["status"] for s in doc["sequences"].values()} == {"ok"}
    steps = {"source", "collide", "retarget", "metrics", "physics"}
    assert all(set(s["steps"]) == steps for s in doc["sequences"].values())
    assert doc["finished"] is not None and doc["writers"] == {}
    # Racing writers may compute the same artifact, but each is published exactly once.
    rows = ArtifactStore(store).computations()
    published = Counter((r["step"], r.get("sequence")) for r in rows if r.get("published"))
    assert set(published.values()) == {1} and len(published) == 8 * len(steps) + 1
    monkeypatch.setenv("EMBODY_WORK_DIR", env["EMBODY_WORK_DIR"])
    capsys.readouterr()
    assert main(["store", "verify", "--store", store, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"checked": 8 * len(steps) + 1, "corrupt": []}
