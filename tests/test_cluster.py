"""The production configuration: Dask scheduler and workers as separate processes, Prefect on
PostgreSQL, bounded task runs per flow run.

The tests start what they need: a PostgreSQL cluster in a temporary folder (`flows.postgres`),
a `prefect server start` on it (`flows.server`), and `dask scheduler` / `dask worker` processes
from Dask's command lines (`flows.cluster`), each worker with its own working directory and
temporary folder. Under `CI=true` a service that cannot start fails the test; elsewhere only a
missing PostgreSQL installation skips it.

They test orchestration, so the steps are cheap: one test runs the real chain with cheap
configs on 3 four-frame sequences; the others use stand-in steps wired like the real chain
(source → collide → shape fit (shared) → retarget → metrics, under names of their own) that compute in microseconds,
with `TOY_SLOW` seconds of sleep per sequence on the workers so a kill lands mid-batch.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from conftest import in_ci
from embody.flows.cluster import DaskProcesses
from embody.flows.postgres import LocalPostgres, postgres_bin
from embody.flows.server import LocalServer
from embody.store import ArtifactStore, Manifest
from embody.tasks.pipeline import Pipeline, Step
from embody.tasks.stages import SOURCE
from toy_flow import Toy, write_amass

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
EMBODY = [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())"]
CHEAP = ["--critic", "none", "--no-render", "--set", "collision.enabled=false",
         "--set", "collision.depth_metrics=false", "--set", "ik.iterations=1",
         "--set", "ik.tracking_iterations=1", "--set", "ik.ramp_iterations=0",
         "--set", "ik.shape_iterations=10", "--set", "fidelity.baseline=false",
         "--set", "run.report=false"]


# -- stand-in steps (imported by the driver subprocess and unpickled on the Dask workers) -------
def _slow() -> None:
    time.sleep(float(os.environ.get("TOY_SLOW", "0")))


def _collide(ctx, inputs):
    _slow()
    pose = inputs["source"].pose
    return Toy(pose[:, :6].copy(), {"mean": float(pose.mean())})


def _fit(ctx, inputs):
    return Toy(np.array([2.0], np.float32), {})


def _retarget(ctx, inputs):
    _slow()
    return Toy(inputs["toy_collide"].x * inputs["toy_fit"].x[0], {})


def _metrics(ctx, inputs):
    return Toy(np.array(float(inputs["toy_retarget"].x.std())),
               {"std": float(inputs["toy_retarget"].x.std())})


# names of their own: a driver warms the real steps' models for the real names
COLLIDE = Step("toy_collide", "1", ("body", "collision"), _collide, Toy.from_arrays, (SOURCE,))
SHAPE_FIT = Step("toy_fit", "1", ("body", "robot", "ik"), _fit, Toy.from_arrays, shared=True)
RETARGET = Step("toy_retarget", "1", ("body", "robot", "ik"), _retarget, Toy.from_arrays,
                (COLLIDE, SHAPE_FIT))
METRICS = Step("toy_metrics", "1", (), _metrics, Toy.from_arrays, (RETARGET,))
TOY = Pipeline(SOURCE, (COLLIDE, SHAPE_FIT, RETARGET, METRICS))


def drive_main() -> None:
    """The driver process: `run_flow(DATA, CONFIG_JSON)` on the stand-in pipeline, summary on
    stdout (a process of its own, so a test can SIGKILL it)."""
    from embody.config import Config
    from embody.flows.dataset import run_flow

    data, config = sys.argv[1], json.loads(sys.argv[2])
    summary = run_flow(data, Config.model_validate(config), pipeline=TOY)
    print(json.dumps({k: summary[k] for k in ("ok", "failed", "failures", "computed")}))


# -- services ------------------------------------------------------------------------------------
def _unavailable(what: str, exc: BaseException | str) -> None:
    message = f"{what} could not start: {exc}"
    if in_ci():
        pytest.fail(f"{message}; CI=true, so this promised check fails instead of skipping",
                    pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="module")
def postgres():
    if postgres_bin() is None:
        _unavailable("PostgreSQL", "initdb not found (apt-get install postgresql)")
    server = LocalPostgres()
    try:
        server.start()
    except Exception as exc:  # installed but unusable: a failure, never a silent skip
        server.stop()
        pytest.fail(f"PostgreSQL could not start: {exc}", pytrace=False)
    yield server
    server.stop()


@pytest.fixture(scope="module")
def prefect_pg(postgres, tmp_path_factory):
    """`prefect server start` with PREFECT_API_DATABASE_CONNECTION_URL=postgresql+asyncpg://…"""
    server = LocalServer(tmp_path_factory.mktemp("prefect-pg") / "home",
                         database_url=postgres.url)
    with server as api:
        yield api


def _pythonpath() -> str:
    """The tests folder (the stand-in steps) and this checkout, before the caller's path."""
    old = os.environ.get("PYTHONPATH")
    return os.pathsep.join([str(TESTS), str(ROOT)] + ([old] if old else []))


def _env(api: str, home: Path) -> dict[str, str]:
    """A driver's environment: the Prefect API and a `PREFECT_HOME` of its own."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_API_URL=api, PREFECT_HOME=str(home), DO_NOT_TRACK="1",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PYTHONPATH=_pythonpath())
    return env


def _cluster(folder: Path, workers: int = 2, slow: float = 0.0,
             preload: bool = True) -> DaskProcesses:
    return DaskProcesses(folder, workers, env={"PYTHONPATH": _pythonpath(),
                                               "TOY_SLOW": str(slow)}, preload=preload)


def _driver(data: Path, cfg: dict, env: dict[str, str], out: Path) -> subprocess.Popen:
    code = (f"import sys; sys.path[:0] = [{str(TESTS)!r}]; import test_cluster; "
            "test_cluster.drive_main()")
    with open(out, "w") as stdout:
        return subprocess.Popen([sys.executable, "-c", code, str(data), json.dumps(cfg)],
                                env=env, cwd=out.parent, stdout=stdout,
                                stderr=subprocess.STDOUT, start_new_session=True)


def _finish(proc: subprocess.Popen, out: Path, timeout: float = 300) -> dict:
    try:
        proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = out.read_text()
    assert proc.returncode == 0, text[-3000:]
    return json.loads(text.strip().splitlines()[-1])


def _api(api: str, path: str, body: dict | None = None) -> list | int:
    import httpx
    reply = httpx.post(f"{api}/{path}", json=body or {}, timeout=30)
    reply.raise_for_status()
    return reply.json()


def _wait_until(what: str, ready, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _cfg(store: Path, name: str, **run) -> dict:
    return {"run": {"store": str(store), "name": name, "batch_size": 3, "report": False,
                    "render": False, "critic": False, **run}}


# -- tests ---------------------------------------------------------------------------------------
def test_embody_run_on_a_dask_cluster_with_prefect_on_postgres(postgres, prefect_pg, tmp_path):
    """`embody run --runner dask --dask-address` on scheduler and workers started from their
    command lines, against a Prefect server whose database is PostgreSQL."""
    data = write_amass(tmp_path / "data", 3, frames=4)
    cluster = _cluster(tmp_path / "cluster")
    with cluster as address:
        workers = {w.pid for w in cluster.workers}
        driver_home = tmp_path / "driver"
        driver_home.mkdir()
        run = subprocess.run(
            [*EMBODY, "run", str(data), "--store", str(tmp_path / "store"), "--name", "prod",
             "--runner", "dask", "--dask-address", address, "--workers", "2", "--json",
             "--no-progress", *CHEAP], env=_env(prefect_pg, driver_home / "prefect"),
            cwd=driver_home, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-3000:]
        assert json.loads(run.stdout)["ok"] == 3
    rows = ArtifactStore(tmp_path / "store").computations()
    # every artifact was computed on a worker, none in the driver
    assert rows and {r["pid"] for r in rows} <= workers
    assert {r["step"] for r in rows} >= {"source", "collide", "shape_fit", "retarget", "metrics"}
    runs = [r for r in _api(prefect_pg, "flow_runs/filter") if r["name"] and
            r["parameters"].get("config", {}).get("run", {}).get("name") == "prod"]
    assert [r["state_type"] for r in runs] == ["COMPLETED"]
    task_runs = _api(prefect_pg, "task_runs/filter",
                     {"flow_runs": {"id": {"any_": [runs[0]["id"]]}}})
    assert task_runs and {t["state_type"] for t in task_runs} == {"COMPLETED"}
    # ... and the server kept them in PostgreSQL
    stored = _sql(postgres, "SELECT count(*) FROM task_run WHERE flow_run_id = $1",
                  runs[0]["id"])
    assert stored == len(task_runs)


def _sql(postgres: LocalPostgres, query: str, *args: object) -> object:
    import asyncio
    import uuid

    import asyncpg

    async def fetch() -> object:
        conn = await asyncpg.connect(postgres.url.replace("+asyncpg", ""))
        try:
            return await conn.fetchval(query, *[uuid.UUID(a) if isinstance(a, str) else a
                                                for a in args])
        finally:
            await conn.close()
    return asyncio.run(fetch())


def test_a_killed_worker_loses_only_its_batch_and_a_rerun_recomputes_only_the_rest(
        prefect_pg, tmp_path):
    n = 12
    data = write_amass(tmp_path / "data", n)
    cluster = _cluster(tmp_path / "cluster", slow=0.3, preload=False)  # stand-ins: no torch
    with cluster as address:
        # 1. SIGKILL a worker in the middle of its batch: the scheduler hands the batch to the
        #    other worker, which finds what the dead one published and computes only the rest.
        store = ArtifactStore(tmp_path / "a")
        victim = cluster.workers[0].pid
        cfg = _cfg(store.root, "a", runner="dask", dask_address=address)
        proc = _driver(data, cfg, _env(prefect_pg, tmp_path / "driver"), tmp_path / "a.out")
        _wait_until("the first worker's first collide", lambda: any(
            r["pid"] == victim and r["step"] == "toy_collide" for r in store.computations()))
        cluster.kill_worker(0)
        killed_at = time.time()
        summary = _finish(proc, tmp_path / "a.out")
        assert (summary["ok"], summary["failed"]) == (n, 0)
        rows = store.computations()
        twice = [k for k, c in Counter((r["step"], r["key"]) for r in rows).items() if c > 1]
        assert twice == []  # nothing the dead worker finished was computed again
        assert Manifest.load(store, "a").keys() == {(s, k) for s, k, _ in store.entries()}
        assert len(rows) == len(store.computations()) == n * 4 + 1
        mine = [r for r in rows if r["pid"] == victim]
        assert mine and all(r["time"] <= killed_at for r in mine)
        assert {r["pid"] for r in rows if r["time"] > killed_at} == {cluster.workers[1].pid}

        # 2. The driver and every worker die at once (the cluster is lost); on fresh workers the
        #    rerun computes exactly what was not in the store.
        cluster.add_worker()
        cluster.wait_for_workers(2)
        store = ArtifactStore(tmp_path / "b")
        cfg = _cfg(store.root, "b", runner="dask", dask_address=address)
        proc = _driver(data, cfg, _env(prefect_pg, tmp_path / "driver"), tmp_path / "b.out")
        _wait_until("half the sequences' retarget",
                    lambda: len(store.computations("toy_retarget")) >= n // 2)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        cluster.kill_worker(1)
        cluster.kill_worker(2)
        at_kill = {(s, k) for s, k, _ in store.entries()}
        before = len(store.computations())
        cluster.add_worker()
        cluster.add_worker()
        cluster.wait_for_workers(2)
        proc = _driver(data, cfg, _env(prefect_pg, tmp_path / "driver"), tmp_path / "b2.out")
        summary = _finish(proc, tmp_path / "b2.out")
    assert (summary["ok"], summary["failed"]) == (n, 0)
    needed = Manifest.load(store, "b").keys()
    assert len(needed) == n * 4 + 1 and at_kill < needed
    rerun = {(r["step"], r["key"]) for r in store.computations()[before:]}
    assert rerun == needed - at_kill
    assert sum(summary["computed"].values()) == len(needed - at_kill)


def test_task_runs_per_flow_run_stay_under_the_bound(prefect_pg, tmp_path):
    """`run.max_task_runs=9` on 12 one-sequence batches of 4 per-sequence steps and a shared
    one: 49 task runs, in subflow runs of at most 9 each (2 batches: 8, the first 9)."""
    n, bound = 12, 9
    data = write_amass(tmp_path / "data", n)
    store = ArtifactStore(tmp_path / "store")
    cfg = _cfg(store.root, "bounded", batch_size=1, max_task_runs=bound, workers=2,
               worker_processes=False)
    before = {r["id"] for r in _api(prefect_pg, "flow_runs/filter")}
    proc = _driver(data, cfg, _env(prefect_pg, tmp_path / "driver"), tmp_path / "out")
    summary = _finish(proc, tmp_path / "out")
    assert (summary["ok"], summary["failed"]) == (n, 0)
    runs = [r for r in _api(prefect_pg, "flow_runs/filter") if r["id"] not in before]
    assert len(runs) == 1 + 6 and {r["state_type"] for r in runs} == {"COMPLETED"}
    per_run = {r["id"]: len(_api(prefect_pg, "task_runs/filter",
                                 {"flow_runs": {"id": {"any_": [r["id"]]}}})) for r in runs}
    chunks = [r for r in runs if r["name"].startswith("bounded chunk ")]
    assert len(chunks) == 6 and all(r["parent_task_run_id"] for r in chunks)
    assert max(per_run.values()) <= bound
    # the chunks hold every step's task run: 4 steps × 12 batches + the shape fit
    assert sum(per_run[r["id"]] for r in chunks) == 4 * n + 1
    assert {(s, k) for s, k, _ in store.entries()} == Manifest.load(store, "bounded").keys()


def test_cluster_workers_are_single_threaded(tmp_path):
    """A `dask worker --nthreads 1 --preload embody.flows.preload` of `DaskProcesses` runs one
    task at a time and every pool its compute could use (torch intra- and inter-op, numba,
    BLAS, OpenMP, the render's software GL) has one thread: the benchmarks count one core per
    worker. Dask's profiler, which samples the task's stack from a second thread, is off."""
    cluster = _cluster(tmp_path / "cluster", workers=1)
    with cluster:
        counts = cluster.thread_counts()
    assert len(counts) == 1
    (worker,) = counts.values()
    assert {k: worker[k] for k in ("dask", "torch", "torch_interop", "numba")} == \
        {"dask": 1, "torch": 1, "torch_interop": 1, "numba": 1}
    assert any(p.startswith("blas:") for p in worker["pools"])
    assert all(p.endswith(":1") for p in worker["pools"]), worker["pools"]
    assert worker["profiler"] is False  # the preload turns Dask's stack sampler off
    assert worker["llvmpipe"] == "0"     # Mesa rasterises on the calling thread
    assert worker["tick_ms"] == 1000     # Dask's housekeeping at batch-cluster intervals
    assert worker["monitor_ms"] == 5000
