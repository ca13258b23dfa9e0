"""The thread runner's workers computing in processes of their own (`embody.tasks.workers`):
the same artifacts as in-thread, each worker in one forked process, the driver's environment
and working directory in them, a worker that dies failing only its batch, and the fallback to
in-thread computing for pipelines that do not pickle."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from embody.config import Config
from embody.store import ArtifactStore, Manifest
from embody.tasks.pipeline import Pipeline, Step
from embody.tasks.stages import SOURCE
from embody.tasks.workers import cpu_seconds, process_cpu_seconds, usable
from toy_flow import Toy, write_amass

N_SEQ = 8



def _where(ctx, inputs):
    """Smooths the pose and says which process computed it, with what environment."""
    kill = os.environ.get("TOY_KILL_MARK")
    if kill and Path(kill).exists() and inputs["source"].pose.shape[0] == 7:
        Path(kill).unlink()  # once: a rerun computes it
        os.kill(os.getpid(), signal.SIGKILL)
    p = inputs["source"].pose.copy()
    p[1:-1] = (p[:-2] + p[1:-1] + p[2:]) / 3
    return Toy(p, {"pid": os.getpid(), "mark": os.environ.get("TOY_MARK", ""),
                   "cwd": os.getcwd()})


def _sum(ctx, inputs):
    return Toy(np.array(float(inputs["collide"].x.sum())), {"pid": os.getpid()})


COLLIDE = Step("collide", "1", ("body",), _where, Toy.from_arrays, (SOURCE,))
METRICS = Step("metrics", "1", (), _sum, Toy.from_arrays, (COLLIDE,))
TOY = Pipeline(SOURCE, (COLLIDE, METRICS))


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    # seq005 (7 frames) is the one a worker dies on
    return write_amass(tmp_path_factory.mktemp("workers") / "data", N_SEQ, frames_of={5: 7})


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _run(data, store: Path, pipeline=TOY, name="toy", **run):
    from embody.flows.dataset import run_flow
    cfg = Config.model_validate({"run": {"store": str(store), "batch_size": 2, "name": name,
                                         "workers": 2, "report": False, **run}})
    return run_flow(data, cfg, pipeline=pipeline)


def _metrics(store: Path, run: str, step: str) -> dict[str, dict]:
    seqs = Manifest.load(ArtifactStore(store), run).sequences
    return {sid: s["metrics"].get(step, {}) for sid, s in seqs.items()}


def _arrays(store: Path) -> dict[str, dict[str, bytes]]:
    s = ArtifactStore(store)
    return {f"{r['step']}/{r['sequence']}": {k: np.asarray(v).tobytes() for k, v in
                                             s.read(r["step"], r["key"]).arrays.items()}
            for r in s.computations()}


def _usable(**sections) -> bool:
    return usable(Config.model_validate(sections))


def test_usable_only_for_several_thread_workers_without_a_vlm_critic():
    assert _usable(run={"workers": 2})
    assert not _usable(run={"workers": 1})
    assert not _usable(run={"runner": "dask"}) and not _usable(run={"runner": "processes"})
    assert not _usable(run={"worker_processes": False})
    # the VLM's request budget is one counter for the run: one client, in the driver
    assert not _usable(critic={"kind": "vlm"})
    assert _usable(critic={"kind": "vlm"}, run={"critic": False})


def test_workers_compute_in_two_processes_what_the_threads_compute(
        prefect_harness, data, tmp_path, monkeypatch):
    monkeypatch.setenv("TOY_MARK", "from-the-driver")  # set after the zygote may have started
    before = cpu_seconds()
    procs = _run(data, tmp_path / "procs")
    threads = _run(data, tmp_path / "threads", worker_processes=False)
    assert procs["ok"] == threads["ok"] == N_SEQ
    pids = {m["pid"] for m in _metrics(tmp_path / "procs", "toy", "collide").values()}
    pids |= {m["pid"] for m in _metrics(tmp_path / "procs", "toy", "metrics").values()}
    assert os.getpid() not in pids and len(pids) == 2  # one process per worker
    in_thread = _metrics(tmp_path / "threads", "toy", "collide").values()
    assert {m["pid"] for m in in_thread} == {os.getpid()}
    for m in _metrics(tmp_path / "procs", "toy", "collide").values():
        assert m["mark"] == "from-the-driver" and m["cwd"] == str(tmp_path)
    assert _arrays(tmp_path / "procs") == _arrays(tmp_path / "threads")
    assert cpu_seconds() > before  # the workers' CPU, as they reported it when the run closed


def test_a_worker_that_dies_fails_its_batch_and_the_run_goes_on(
        prefect_harness, data, tmp_path, monkeypatch):
    mark = tmp_path / "kill-once"
    mark.touch()
    monkeypatch.setenv("TOY_KILL_MARK", str(mark))
    out = _run(data, tmp_path / "store")
    assert not mark.exists()  # the worker killed itself on seq005
    failed = {f["id"]: f for f in out["failures"]}
    assert "seq005" in failed and failed["seq005"]["step"] == "collide"
    assert "exited while computing step 'collide'" in failed["seq005"]["error"]
    assert set(failed) <= {"seq004", "seq005"}  # its batch (of 2), nothing else
    assert out["ok"] == N_SEQ - len(failed)
    # the other worker (or a thread itself, when it found no free worker) did the rest
    done = [m for sid, m in _metrics(tmp_path / "store", "toy", "metrics").items()
            if sid not in failed]
    assert len(done) == out["ok"] and all("pid" in m for m in done)
    again = _run(data, tmp_path / "store", name="toy-again")  # a rerun computes what failed
    assert again["ok"] == N_SEQ and again["failed"] == 0


def _lambda_pipeline() -> Pipeline:
    step = Step("collide", "1", ("body",), lambda ctx, inputs: _where(ctx, inputs),
                Toy.from_arrays, (SOURCE,))
    return Pipeline(SOURCE, (step,))


def test_a_pipeline_that_does_not_pickle_is_computed_in_the_threads(
        prefect_harness, data, tmp_path):
    out = _run(data, tmp_path / "store", pipeline=_lambda_pipeline())
    assert out["ok"] == N_SEQ
    assert {m["pid"] for m in _metrics(tmp_path / "store", "toy", "collide").values()} == {
        os.getpid()}


def test_a_call_waits_for_the_worker_that_had_its_sequences_unless_a_free_one_is_unwanted():
    import threading
    import time

    from embody.tasks.workers import _Pool, _Worker
    a, b = _Worker(101, None), _Worker(102, None)
    pool = _Pool([a, b])
    assert pool._take(["s1", "s2"]) is a  # nothing known: the first free one
    pool._give(a, ["s1", "s2"])
    assert pool._take(["s3"]) is a
    pool._give(a, ["s3"])
    pool._last.update(s4=102, s5=102)
    assert pool._take(["s4", "s5", "s1"]) is b  # two of three were last on b
    # b is busy and no waiting call wants a: a takes the call (no worker idles)
    assert pool._take(["s4"]) is a
    pool._give(a, ["s3"])
    assert pool._take(["s6"]) is a  # a call of new sequences: the free worker
    got: dict[str, object] = {}

    def call(name: str, ids: list[str]) -> None:
        got[name] = pool._take(ids)

    def waiting(n: int) -> None:
        deadline = time.monotonic() + 10
        while len(pool._waiting) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(pool._waiting) == n

    # both busy: a call of b's sequences waits for b, one of a's for a
    for_b = threading.Thread(target=call, args=("b", ["s5"]))
    for_b.start()
    waiting(1)
    for_a = threading.Thread(target=call, args=("a", ["s3"]))
    for_a.start()
    waiting(2)
    pool._give(a, ["s6"])  # a is free: the call that wants it takes it, the other waits on
    for_a.join(10)
    assert got["a"] is a and for_b.is_alive()
    b.dead = True  # b's call now wants no worker in particular: the next free one
    pool._give(b, ["s4", "s5", "s1"])
    waiting(1)
    assert for_b.is_alive()
    pool._give(a, ["s3"])
    for_b.join(10)
    assert got["b"] is a
    assert pool._last["s1"] == 102
    pool._give(a, ["s5"])
    assert pool._take(["s1"]) is a  # a dead worker is never chosen
    a.dead = True
    assert pool._take(["s1"]) is None  # none alive: the caller computes itself


def test_a_step_without_affinity_leaves_its_sequences_with_the_worker_they_had():
    import threading
    from multiprocessing import Pipe

    from embody.tasks.stages import COLLIDE as REAL_COLLIDE, RENDER, RENDER_REFINED
    from embody.tasks.workers import _Pool, _Worker
    assert not RENDER.affinity and not RENDER_REFINED.affinity and REAL_COLLIDE.affinity
    ends = [Pipe() for _ in range(2)]

    def answer(conn) -> None:  # the worker's side of the pipe: each batch answered at once
        while (msg := conn.recv()) is not None:
            conn.send(("ok", msg[2]))

    for _, theirs in ends:
        threading.Thread(target=answer, args=(theirs,), daemon=True).start()
    a, b = _Worker(101, ends[0][0]), _Worker(102, ends[1][0])
    pool = _Pool([a, b])
    records = [{"id": "s1"}]
    assert pool.call("batch", "collide", records, {}) == (True, records)
    assert pool._last["s1"] == 101
    pool._busy.add(101)  # a busy: the render call takes b, which is not remembered
    assert pool.call("batch", "render", records, {}, affinity=False) == (True, records)
    assert pool._last["s1"] == 101
    pool._busy.discard(101)
    assert pool._take(["s1"]) is a
    for ours, _ in ends:
        ours.send(None)


def test_the_thread_runner_has_a_thread_per_batch_in_flight_only_with_worker_processes():
    from embody.tasks.workers import task_threads
    assert task_threads(Config.model_validate({"run": {"workers": 3}})) == 6
    assert task_threads(Config.model_validate({"run": {"workers": 3, "worker_processes": False}})) == 3
    assert task_threads(Config.model_validate({"run": {"workers": 1}})) == 1


def test_process_cpu_seconds_reads_a_running_process_and_zero_for_a_gone_one():
    spent = sum(i * i for i in range(2_000_000))  # some CPU of our own first
    assert spent > 0 and process_cpu_seconds(os.getpid()) > 0
    assert process_cpu_seconds(2 ** 22 + 7) == 0.0  # beyond Linux's pid range
