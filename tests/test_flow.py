"""The dataset flow on a cheap stand-in pipeline: caching, failure isolation, resume, Dask parity.

The stand-in steps have the real steps' names, config sections and wiring (tasks/stages.py), so
what is (re)computed here is what the real chain would recompute; they just run in microseconds.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from embody.config import Config
from embody.store import ArtifactStore, Manifest
from embody.tasks.execute import new_record, run_batch
from embody.tasks.pipeline import Context, Pipeline, Step
from embody.tasks.stages import SOURCE
from toy_flow import Toy, write_amass

N_SEQ = 7


def _smooth(ctx, inputs):
    if os.environ.get("TOY_SLOW"):
        time.sleep(float(os.environ["TOY_SLOW"]))
    p = inputs["source"].pose.copy()
    p[1:-1] = (p[:-2] + p[1:-1] + p[2:]) / 3
    return Toy(p, {"mean_abs": float(np.abs(p).mean())})


def _fit(ctx, inputs):
    return Toy(np.array([1.0 + len(ctx.cfg.robot.name) / 100], np.float32), {})


def _ik(ctx, inputs):
    x = inputs["collide"].x[:, :22].reshape(len(inputs["collide"].x), -1)
    return Toy(x * inputs["shape_fit"].x[0], {"rms": float(np.sqrt((x ** 2).mean()))})


def _metrics(ctx, inputs):
    return Toy(np.array(float(inputs["retarget"].x.std())), {"std": float(inputs["retarget"].x.std())})


COLLIDE = Step("collide", "1", ("body", "collision"), _smooth, Toy.from_arrays, (SOURCE,))
SHAPE_FIT = Step("shape_fit", "1", ("body", "robot", "ik"), _fit, Toy.from_arrays, shared=True)
RETARGET = Step("retarget", "1", ("body", "robot", "ik"), _ik, Toy.from_arrays,
                (COLLIDE, SHAPE_FIT))
METRICS = Step("metrics", "1", (), _metrics, Toy.from_arrays, (RETARGET,))
TOY = Pipeline(SOURCE, (COLLIDE, SHAPE_FIT, RETARGET, METRICS))


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the run's report goes to ./reports/<run>


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_amass(tmp_path_factory.mktemp("toy") / "data", N_SEQ)


def _cfg(store: Path, **run) -> Config:
    return Config.model_validate({"run": {"store": str(store), "batch_size": 3, "name": "toy",
                                          **run}})


def _computed(store: ArtifactStore) -> list[tuple[str, str | None]]:
    return sorted((r["step"], r.get("sequence")) for r in store.computations())


def _flow(data, cfg):
    from embody.flows.dataset import run_flow
    return run_flow(data, cfg, pipeline=TOY)


# -- task logic without Prefect (the task's body is `run_batch`) ---------------------------------
def test_batch_step_hits_do_no_work(data, tmp_path):
    from embody.io import load_dataset
    from embody.tasks.steps import _batch

    ctx = Context(cfg=_cfg(tmp_path), store_root=str(tmp_path), run="unit")
    refs = list(load_dataset(data))[:2]
    first = _batch.fn(SOURCE, ctx, [new_record(r) for r in refs], {})
    assert [r["computed"] for r in first] == [["source"], ["source"]]
    assert all("ref" not in r for r in first)
    again = run_batch(SOURCE, ctx, [new_record(r) for r in refs], {})
    assert [r["computed"] for r in again] == [[], []]
    assert [r["keys"] for r in again] == [r["keys"] for r in first]
    # (the toy clip's random poses also draw a layout warning, stored beside these)
    assert {k: again[0]["metrics"]["source"][k] for k in ("frames", "fps")} == {"frames": 6, "fps": 30.0}
    col = run_batch(COLLIDE, ctx, first, {})
    assert [r["computed"] for r in col] == [["source", "collide"]] * 2
    # a missing shared input fails the sequence, not the batch call
    bad = run_batch(RETARGET, ctx, col, {})
    assert [r["status"] for r in bad] == ["failed", "failed"]
    assert bad[0]["failed_step"] == "retarget" and "KeyError" in bad[0]["error"]
    assert len(ArtifactStore(tmp_path).computations()) == 4


def test_resource_is_built_once_when_threads_ask_at_once():
    import threading

    from embody.tasks.pipeline import resource
    built = []

    def factory():
        time.sleep(0.2)
        built.append(1)
        return object()
    got = []
    threads = [threading.Thread(target=lambda: got.append(resource("test", "once", factory)))
               for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(built) == 1 and len({id(g) for g in got}) == 1


# -- flows (one shared Prefect harness) ----------------------------------------------------------
def test_failure_isolation_then_resume(prefect_harness, data, tmp_path):
    store = ArtifactStore(tmp_path)
    cfg = _cfg(tmp_path).model_copy(update={"debug": Config().debug.model_copy(
        update={"fail_on": ["seq002"]})})
    summary = _flow(data, cfg)
    assert (summary["total"], summary["ok"], summary["failed"]) == (N_SEQ, N_SEQ - 1, 1)
    assert summary["failures"][0]["id"] == "seq002"
    assert summary["failures"][0]["step"] == "collide"
    assert "InjectedFailure" in summary["failures"][0]["error"]
    manifest = Manifest.load(store, "toy")
    assert manifest.sequences["seq002"]["status"] == "failed"
    assert set(manifest.sequences["seq002"]["steps"]) == {"source"}
    assert manifest.sequences["seq003"]["status"] == "ok"
    assert set(manifest.sequences["seq003"]["steps"]) == {"source", "collide", "retarget", "metrics"}
    before = _computed(store)
    assert before.count(("collide", "seq003")) == 1 and ("collide", "seq002") not in before
    table = Path(summary["table"]).read_text().splitlines()
    assert table[0].startswith("id,status") and len(table) == N_SEQ + 1

    summary = _flow(data, _cfg(tmp_path))  # the same run without the injected failure
    assert summary["failed"] == 0
    new = sorted(set(_computed(store)) - set(before))
    assert len(_computed(store)) - len(before) == 3
    assert new == [("collide", "seq002"), ("metrics", "seq002"), ("retarget", "seq002")]
    assert summary["computed"] == {"source": 0, "shape_fit": 0, "collide": 1, "retarget": 1,
                                   "metrics": 1}


def test_config_change_recomputes_only_dependent_steps(prefect_harness, data, tmp_path):
    store = ArtifactStore(tmp_path)
    _flow(data, _cfg(tmp_path))
    n0 = len(store.computations())
    assert n0 == 1 + 4 * N_SEQ
    warm = _flow(data, _cfg(tmp_path))
    assert len(store.computations()) == n0 and sum(warm["computed"].values()) == 0
    cfg = _cfg(tmp_path).model_copy(update={"robot": Config().robot.model_copy(
        update={"name": "other_robot"})})
    _flow(data, cfg)
    steps = [r["step"] for r in store.computations()[n0:]]
    assert sorted(set(steps)) == ["metrics", "retarget", "shape_fit"]
    assert (steps.count("shape_fit"), steps.count("retarget"), steps.count("metrics")) == (
        1, N_SEQ, N_SEQ)


_KILLED_RUN = """
import sys
sys.path.insert(0, sys.argv[1])
from test_flow import TOY, _cfg
from embody.flows.dataset import run_flow
from pathlib import Path
run_flow(sys.argv[2], _cfg(Path(sys.argv[3]), workers=1, batch_size=1), pipeline=TOY)
"""


def test_killed_run_resumes_without_recomputing(prefect_harness, data, tmp_path):
    store = ArtifactStore(tmp_path)
    env = dict(os.environ, PREFECT_API_URL=prefect_harness, TOY_SLOW="0.4")
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_RUN, str(Path(__file__).parent),
                             str(data), str(tmp_path)], env=env, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(store.computations("metrics")) < 2:
        assert proc.poll() is None, "the run ended before it could be killed"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done = {(r["step"], r["key"]) for r in store.computations() if r["published"]}
    assert 2 <= len(store.computations("metrics")) < N_SEQ
    manifest = json.loads((store.runs_dir / "toy" / "manifest.json").read_text())
    assert manifest["finished"] is None  # valid JSON, marked unfinished
    assert manifest["shared"]["shape_fit"]  # the shared fit is recorded as soon as it exists
    from embody.cli import main
    assert main(["store", "gc", "--store", str(tmp_path)]) == 0  # the killed run is live: kept
    assert done <= {(s, k) for s, k, _ in store.entries()}

    summary = _flow(data, _cfg(tmp_path))
    assert summary["ok"] == N_SEQ
    redone = [(r["step"], r["key"]) for r in store.computations()]
    assert all(redone.count(item) == 1 for item in done)  # nothing finished was recomputed
    assert {s for s, _ in redone} == {"source", "collide", "shape_fit", "retarget", "metrics"}
    assert len(store.computations("metrics")) == N_SEQ


def _artifact_bytes(store: ArtifactStore) -> dict[tuple[str, str], dict[str, bytes]]:
    return {(s, k): {n: a.tobytes() for n, a in store.read(s, k).arrays.items()}
            for s, k, _ in store.entries()}


def test_dask_matches_threads(prefect_harness, data, tmp_path):
    threads = _flow(data, _cfg(tmp_path / "threads"))
    dask = _flow(data, _cfg(tmp_path / "dask", runner="dask", workers=2))
    assert dask["ok"] == threads["ok"] == N_SEQ
    a, b = ArtifactStore(tmp_path / "threads"), ArtifactStore(tmp_path / "dask")
    ma, mb = Manifest.load(a, "toy"), Manifest.load(b, "toy")
    assert {i: s["steps"] for i, s in ma.sequences.items()} == {
        i: s["steps"] for i, s in mb.sequences.items()}
    assert _artifact_bytes(a) == _artifact_bytes(b)
    assert len({r["pid"] for r in b.computations()} - {os.getpid()}) >= 1  # ran in workers


def test_progress_lines_and_terminal_bars():
    import io

    from embody.flows.progress import Progress

    plain = io.StringIO()
    bar = Progress(["source", "collide"], 20, stream=plain)
    for _ in range(20):
        bar.add("source", done=1, cached=1)
    bar.add("collide", failed=20)
    lines = plain.getvalue().splitlines()
    assert len(lines) == 12  # every tenth, not every batch
    assert lines[-2].split() == ["source", "[########################]", "20/20", "cached", "20",
                                 "failed", "0"]
    assert lines[-1].endswith("20/20  cached 0  failed 20")

    class Tty(io.StringIO):
        def isatty(self):
            return True

    tty = Tty()
    bar = Progress(["source", "collide"], 4, stream=tty)
    bar.add("source", done=2)
    bar.add("collide", done=1)
    assert tty.getvalue().count("\x1b[2F") == 1  # redrawn in place
    assert tty.getvalue().rstrip("\n").endswith("collide [######                  ] 1/4  "
                                                 "cached 0  failed 0\x1b[K")
