"""Dataset-scale benchmark: N short synthetic sequences through `embody run` on a real Prefect server.

Every run is a separate `embody run` process (the default pipeline: source → collide →
shape_fit → retarget → refine (geometric critic) → metrics) pointed at one persistent
`prefect server start` (its own PREFECT_HOME, SQLite), sampled with psutil every 0.2 s:

1. cold, `--runner processes`, W workers, N sequences → seq_per_min, driver / worker peak RSS,
   task runs, driver and server CPU seconds
2. warm rerun of (1)                                   → warm_s (every step a store hit)
3. cold, `--runner dask` (LocalCluster, W workers)     → seq_per_min_dask
4. 1 vs 2 workers (processes) on alternating chunks of fresh sequences, order 2,1,1,2,…
   (the machine is shared: a load change hits both alike; the mean load is printed)
                                                       → seq_per_min_1worker, ratio_2w_1w
5. cold (processes, W workers) killed with SIGKILL (driver and workers) once half the sequences
   have their metrics, then rerun: resumed_recomputed (artifacts computed by the rerun) against
   unfinished_at_kill (artifacts of the finished run that were not in the store at the kill).

The figures measure orchestration, so per-sequence compute is made tiny, through config only,
and the output says so: render off (benchmarks/render.py measures it), no end-of-run report
(benchmarks/report.py), sequences of `--frames` (default 20) frames, and every step kept but
cheap (`CHEAP`: collision detection without the optimiser or the depth judge, one IK
iteration, a 10-step shape fit, one critic round, no fidelity IK baseline). `api_errors`
counts 5xx / "database is locked" / tracebacks in the server log and in the runs' stderr. Peak RSS: the driver process alone; workers: the largest
child process (Prefect process-pool workers, Dask nanny/worker processes).

    python benchmarks/scale.py [--n 1000] [--frames 20] [--workers 2] [--batch-size 16] [--out DIR]

`--full` is the production-shaped run instead (`full_run`): N sequences of the default synthetic
dataset (default lengths, default stage configs, render on; the end-of-run report off) through
`embody run --runner dask --dask-address` on a `dask scheduler` and W `dask worker` processes
started from their command lines (`embody.flows.cluster`), with the Prefect server on a
throwaway PostgreSQL (`embody.flows.postgres`) and the store given by `--store-url` (default a
local folder). It prints seq/min, the driver's and the workers' peak RSS, API errors, the
store's files (objects) and bytes per sequence, the most task runs any flow run held, the
workers' CPU seconds per sequence, and the hours the same rate needs for 1,000 and 20,000
sequences. With `--store-url s3://bucket/prefix` and no `AWS_ENDPOINT_URL`, it starts a moto S3
server on localhost and counts, from the server's own access log, the HTTP requests the run
(driver and workers) sent per sequence (`store_requests_per_seq`):

    python benchmarks/scale.py --full --n 1000 [--store-url s3://bench/full]   # hours on 2 cores

`--full --compare-workers` measures what a second single-threaded worker buys
(`compare_workers`): the same `--chunk` default-config sequences on fresh clusters of 2, 1, 1,
2 workers (ABBA), rates over the steady spans, with the CPU seconds per sequence of the
workers, their steps, the driver, the scheduler and the Prefect server, so a loaded machine
can be told apart from a serial part:

    python benchmarks/scale.py --full --compare-workers --chunk 8 --rounds 2 --batch-size 2

`--database sqlite` puts the `--full` runs' Prefect server on its own SQLite file (for a
machine where no PostgreSQL runs; the RESULT line says which); `--set KEY=VALUE` (repeatable)
is passed to every `embody run` and listed in the RESULT line's `configs=`.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: The figures' stage configs: every step of the default pipeline runs (collision detection,
#: shape fit, IK, one critic round, MuJoCo-validated metrics) with minimal work, so the run
#: measures orchestration (Prefect, store, driver), not robotics: the collision optimiser and
#: the mesh depth judge off, one IK iteration, a 10-step shape fit, no fidelity IK baseline.
CHEAP = ["--set", "collision.enabled=false", "--set", "collision.depth_metrics=false",
         "--set", "ik.iterations=1", "--set", "ik.tracking_iterations=1",
         "--set", "ik.ramp_iterations=0",
         "--set", "ik.shape_iterations=10", "--set", "critic.rounds=1",
         "--set", "fidelity.baseline=false"]
#: An HTTP 5xx (access-log status or reason), SQLite locking, a traceback. Not a bare "50x ":
#: log timestamps' milliseconds (",501 - ") matched that and counted Dask shutdown warnings.
_ERRORS = re.compile(r"database is locked|HTTPStatusError|Service Unavailable|Internal Server Error"
                     r"|OperationalError|Traceback|HTTP/\d(?:\.\d)?\" 5\d\d|status(?: code)? 5\d\d",
                     re.I)
EMBODY = [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())"]


def write_dataset(folder: Path, n: int, frames: int, seed: int = 0, bases: int = 50) -> Path:
    """`n` distinct sequences of `frames` frames: windows of `bases` synthetic sequences
    (embody.synth), sequence i = base i % bases from frame i // bases (so every file's bytes,
    hence every content key, differ); generating 1,000 full sequences alone took minutes."""
    done = folder / ".complete"
    if done.is_file():
        return folder
    from embody.io import save
    from embody.synth.generator import generate_sequence
    from embody.synth.kinematics import ArmIK

    folder.mkdir(parents=True, exist_ok=True)
    ik = ArmIK()
    motions = [generate_sequence(seed, b, ik) for b in range(min(n, bases))]
    for i in range(n):
        m = motions[i % len(motions)]
        f = min(frames, m.num_frames)
        start = (i // len(motions)) % max(1, m.num_frames - f + 1)
        save(replace(m, pose=m.pose[start:start + f], transl=m.transl[start:start + f]),
             folder / f"seq_{i:05d}.npz")
    done.write_text("ok")
    return folder


def _tree_rss(proc: Any, cpu: dict[int, float] | None = None) -> tuple[int, int]:
    """(driver RSS, largest child RSS) in bytes; `cpu` collects each child's CPU seconds."""
    import psutil
    try:
        driver = proc.memory_info().rss
        kids = proc.children(recursive=True)
    except psutil.Error:
        return 0, 0
    worst = 0
    for k in kids:
        try:
            worst = max(worst, k.memory_info().rss)
            if cpu is not None:
                cpu[k.pid] = max(cpu.get(k.pid, 0.0), _cpu_s(k))
        except psutil.Error:
            pass
    return driver, worst


def step_seconds(store: Path, n: int) -> dict[str, float]:
    """Each step's recorded compute seconds per sequence (the shared shape fit divided by n)."""
    from embody.store import ArtifactStore
    out: dict[str, float] = {}
    for row in ArtifactStore(store).computations():
        out[row["step"]] = out.get(row["step"], 0.0) + float(row.get("compute_s") or 0.0)
    return {k: round(v / n, 3) for k, v in out.items()}


def count_task_runs(api: str) -> int:
    import httpx
    r = httpx.post(api + "/task_runs/count", json={}, timeout=60)
    r.raise_for_status()
    return int(r.json())


def _cpu_s(proc: Any) -> float:
    try:
        t = proc.cpu_times()
        return float(t.user + t.system)
    except Exception:
        return 0.0


class Bench:
    def __init__(self, args: argparse.Namespace, work: Path, api: str, server: Any) -> None:
        self.args, self.work, self.api, self.server = args, work, api, server
        self.server_log = server.log_path
        self.data = write_dataset(work / f"data-n{args.n}-f{args.frames}", args.n, args.frames)
        self.env = dict(os.environ, PREFECT_API_URL=api, PYTHONPATH=str(ROOT), DO_NOT_TRACK="1",
                        PREFECT_SERVER_ANALYTICS_ENABLED="false", OMP_NUM_THREADS="1",
                        MKL_NUM_THREADS="1")
        self.errors = 0

    def command(self, store: Path, runner: str, workers: int, extra: list[str]) -> list[str]:
        a = self.args
        return [*EMBODY, "run", str(self.data), "--store", str(store), "--name", "scale",
                "--runner", runner, "--workers", str(workers), "--batch-size", str(a.batch_size),
                "--no-render", "--set", "run.report=false", "--no-progress", "--json",
                *CHEAP, *extra]

    def _server_cpu(self) -> float:
        import psutil
        try:
            p = psutil.Process(self.server.proc.pid)
            return _cpu_s(p) + sum(_cpu_s(c) for c in p.children(recursive=True))
        except Exception:
            return 0.0

    def run(self, label: str, store: Path, runner: str, workers: int, n: int | None = None,
            offset: int = 0, kill_at: int | None = None) -> dict[str, Any]:
        """One `embody run` over `n` sequences from `offset`, sampled; `kill_at`: SIGKILL its
        group once that many sequences have their metrics artifact."""
        import psutil
        from embody.store import ArtifactStore

        n = n or self.args.n
        extra = ["--set", f"run.offset={offset}", "--limit", str(n)]
        log_before = self.server_log.stat().st_size if self.server_log.is_file() else 0
        tasks_before = count_task_runs(self.api)
        server_cpu0 = self._server_cpu()
        load0 = os.getloadavg()[0]
        err_path = self.work / f"{label}.stderr"
        out_path = self.work / f"{label}.json"
        t0, started = time.perf_counter(), time.time()
        # stdout to a file, not a pipe: `--json` of 1,000 sequences is ~110 KB, more than a pipe
        # buffer, and the driver would block on it while this loop only polls.
        with open(err_path, "w") as err, open(out_path, "w") as stdout:
            proc = subprocess.Popen(self.command(store, runner, workers, extra), env=self.env,
                                    cwd=self.work, stdout=stdout, stderr=err, text=True,
                                    start_new_session=True)
            ps = psutil.Process(proc.pid)
            peak_driver = peak_worker = 0
            driver_cpu = 0.0
            kids_cpu: dict[int, float] = {}
            loads = [load0]
            killed = False
            metrics = store / "counters" / "metrics.jsonl"
            try:
                while proc.poll() is None:
                    d, w = _tree_rss(ps, kids_cpu)
                    peak_driver, peak_worker = max(peak_driver, d), max(peak_worker, w)
                    driver_cpu = max(driver_cpu, _cpu_s(ps))
                    loads.append(os.getloadavg()[0])
                    if kill_at is not None and metrics.is_file() and \
                            sum(1 for _ in metrics.open()) >= kill_at:
                        os.killpg(proc.pid, signal.SIGKILL)
                        killed = True
                        break
                    time.sleep(0.2)
                proc.wait()
            finally:  # the benchmark interrupted: leave no run behind
                if proc.poll() is None:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
        wall = time.perf_counter() - t0
        if killed:  # the group's children (workers) die with it; wait until they are gone
            for _ in range(100):
                try:
                    os.killpg(proc.pid, 0)
                except ProcessLookupError:
                    break
                time.sleep(0.1)
        out = out_path.read_text()
        summary = json.loads(out) if out.strip() and not killed else {}
        new_log = b""
        if self.server_log.is_file():
            with open(self.server_log, "rb") as f:
                f.seek(log_before)
                new_log = f.read()
        errors = sum(bool(_ERRORS.search(line)) for line in
                     new_log.decode(errors="replace").splitlines() + err_path.read_text(
                         errors="replace").splitlines())
        self.errors += errors
        tasks = count_task_runs(self.api) - tasks_before
        server_cpu = self._server_cpu() - server_cpu0
        rows = [r for r in ArtifactStore(store).computations() if r["time"] >= started]
        done = [r["time"] for r in rows if r["step"] == "metrics"]
        # Sequences per minute from the first computed artifact to the last finished sequence:
        # the rate without process start-up (imports, worker spawn), which N does not change.
        span = (max(done) - min(r["time"] for r in rows)) if len(done) > 2 else None
        compute = sum(float(r.get("compute_s") or 0.0) for r in rows)
        res = {"label": label, "n": n, "workers": workers, "runner": runner,
               "wall_s": round(wall, 2), "seq_per_min": round(60 * n / wall, 2),
               "steady_done": len(done), "steady_span_s": round(span, 2) if span else None,
               "steady_seq_per_min": round(60 * len(done) / span, 2) if span else None,
               "compute_s": round(compute, 1),
               # worker time not spent in a step's compute (Prefect task-run handling, pickling,
               # store reads, waiting for the driver), per task run; inflated by CPU contention
               "noncompute_s_per_task_run": round((span * workers - compute) / tasks, 3)
               if span and tasks else None,
               "driver_cpu_s": round(driver_cpu, 1), "server_cpu_s": round(server_cpu, 1),
               # CPU (not wall) seconds of the worker processes (sampled, start-up included):
               # if it rises per sequence with more workers, the cores are not independent
               "worker_cpu_s": round(sum(kids_cpu.values()), 1),
               "load_avg": round(sum(loads) / len(loads), 1),
               "peak_driver_rss_mb": round(peak_driver / 2**20, 1),
               "peak_worker_rss_mb": round(peak_worker / 2**20, 1), "task_runs": tasks,
               "api_errors": errors, "exit": proc.returncode, "killed": killed,
               "ok": summary.get("ok"), "failed": summary.get("failed"),
               "computed": summary.get("computed"),
               "manifest_kb": round(os.path.getsize(store / "runs" / "scale" / "manifest.json")
                                    / 1024, 1) if (store / "runs/scale/manifest.json").is_file()
               else None,
               "artifacts": sum(1 for _ in ArtifactStore(store).entries())}
        print(json.dumps(res), flush=True)
        if summary.get("failed"):
            print(f"  first failure: {summary['failures'][0]}", flush=True)
        return res


def _rss(pid: int) -> int:
    import psutil
    try:
        return int(psutil.Process(pid).memory_info().rss)
    except psutil.Error:
        return 0


def warm_compute(rows: list[dict[str, Any]]) -> tuple[float, float]:
    """(median compute seconds per sequence summed over the per-sequence steps, the shared
    steps' seconds): a worker's first call of a step also loads or compiles its kernels
    (minutes for numba's cold cache on a loaded machine), which a short run cannot amortise
    and a 1,000-sequence run pays once per worker."""
    import statistics
    per_step: dict[str, list[float]] = {}
    shared = 0.0
    for r in rows:
        if r.get("sequence") is None:
            shared += float(r.get("compute_s") or 0.0)
        else:
            per_step.setdefault(r["step"], []).append(float(r.get("compute_s") or 0.0))
    return sum(statistics.median(v) for v in per_step.values()), shared


def _cpu_tree(pid: int) -> float:
    """CPU seconds of a process and its children (0 when gone)."""
    import psutil
    try:
        p = psutil.Process(pid)
        return _cpu_s(p) + sum(_cpu_s(c) for c in p.children(recursive=True))
    except (psutil.Error, ValueError):  # gone, or no process (-1)
        return 0.0


class S3Counter:
    """`--store-url s3://bucket/...` without `AWS_ENDPOINT_URL`: a moto S3 server on localhost
    (`benchmarks.object_store.start_moto`), the `AWS_*` variables pointing
    at it for this process and the ones it starts; `requests()` counts the HTTP requests the
    server has answered, from its own access log (one line per request): a count independent
    of embody's code. With `AWS_ENDPOINT_URL` set (a real bucket) nothing is counted."""

    def __init__(self, store: str, work: Path) -> None:
        self.store, self.work = store, work
        self.proc: subprocess.Popen | None = None
        self.log = work / "moto.log"

    def __enter__(self) -> "S3Counter":
        if not self.store.startswith("s3://") or os.environ.get("AWS_ENDPOINT_URL"):
            return self
        import socket

        from benchmarks.object_store import start_moto
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        bucket = self.store[len("s3://"):].split("/", 1)[0]
        self.proc = start_moto(port, self.log, bucket)
        os.environ.update(AWS_ENDPOINT_URL=f"http://127.0.0.1:{port}", AWS_ACCESS_KEY_ID="bench",
                          AWS_SECRET_ACCESS_KEY="bench", AWS_REGION="us-east-1")
        print(f"moto S3 server on 127.0.0.1:{port}, bucket {bucket}", flush=True)
        return self

    def requests(self) -> int | None:
        if self.proc is None:
            return None
        from benchmarks.object_store import served_requests
        time.sleep(0.5)  # the last requests' log lines
        return served_requests(self.log)

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait()
            for k in ("AWS_ENDPOINT_URL", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY",
                      "AWS_REGION"):
                os.environ.pop(k, None)


def store_size(store: str) -> tuple[int, int]:
    """(files or objects, bytes) of a store folder or URL."""
    from embody.store.objects import Objects, is_url
    files = size = 0
    if is_url(store) and not store.startswith("file://"):
        for meta in Objects(store).list(""):
            files += 1
            size += int(meta["size"])
        return files, size
    for root, _, names in os.walk(store.removeprefix("file://")):
        for name in names:
            files += 1
            size += os.path.getsize(os.path.join(root, name))
    return files, size


def drive(label: str, cmd: list[str], env: dict[str, str], work: Path, cluster: Any,
          server_pid: int, db_pid: int = -1) -> dict[str, Any]:
    """Run one `embody run` driver to its end, sampling every 0.5 s: its process tree's RSS
    and CPU, the workers' RSS, the load; CPU seconds of the workers, the scheduler and the
    Prefect server spent while it ran."""
    import psutil

    err_path, out_path = work / f"{label}.stderr", work / f"{label}.json"
    pids = {"workers": [w.pid for w in cluster.workers], "scheduler": [cluster.scheduler.pid],
            "server": [server_pid], "database": [db_pid]}
    cpu0 = {k: sum(_cpu_tree(p) for p in v) for k, v in pids.items()}
    started, t0 = time.time(), time.perf_counter()
    peak_driver = peak_worker = 0
    driver_cpu = 0.0
    loads = [os.getloadavg()[0]]
    with open(err_path, "w") as err, open(out_path, "w") as out:
        proc = subprocess.Popen(cmd, env=env, cwd=work, stdout=out, stderr=err,
                                start_new_session=True)
        try:
            ps = psutil.Process(proc.pid)
            while proc.poll() is None:
                try:
                    tree = [ps] + ps.children(recursive=True)
                    peak_driver = max(peak_driver, sum(
                        p.memory_info().rss for p in tree if p.is_running()))
                    driver_cpu = max(driver_cpu, sum(_cpu_s(p) for p in tree))
                except psutil.Error:
                    pass
                peak_worker = max([peak_worker] + [_rss(w.pid) for w in cluster.workers])
                loads.append(os.getloadavg()[0])
                time.sleep(0.5)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    wall = time.perf_counter() - t0
    cpu = {k: sum(_cpu_tree(p) for p in v) - cpu0[k] for k, v in pids.items()}
    summary = json.loads(out_path.read_text() or "{}")
    if summary.get("failed"):
        print(f"  {label}: {summary['failed']} failed; first: {summary['failures'][0]}",
              flush=True)
    errors = 0
    for path in [err_path, *cluster.folder.glob("worker-*/worker.log")]:
        errors += sum(bool(_ERRORS.search(line)) for line in
                      path.read_text(errors="replace").splitlines())
    return {"label": label, "started": started, "wall_s": wall, "summary": summary,
            "peak_driver": peak_driver, "peak_worker": peak_worker, "driver_cpu_s": driver_cpu,
            "worker_cpu_s": cpu["workers"], "scheduler_cpu_s": cpu["scheduler"],
            "server_cpu_s": cpu["server"], "database_cpu_s": cpu["database"],
            "load_avg": sum(loads) / len(loads),
            "errors": errors, "exit": proc.returncode}


def _full_env(api: str, work: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    # this checkout first, then the caller's path (packages installed with `pip --target`)
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH", "")]))
    env.update(PREFECT_API_URL=api, PREFECT_HOME=str(work / "driver-prefect"),
               PYTHONPATH=path, DO_NOT_TRACK="1", PREFECT_SERVER_ANALYTICS_ENABLED="false")
    return env


def _render(args: argparse.Namespace) -> str:
    """The RESULT line's `render=`: what the `--set` overrides leave `run.render` at."""
    from embody.config import load_config

    return "on" if load_config(sets=args.sets).run.render else "off"


def _configs(args: argparse.Namespace) -> str:
    """The RESULT line's `configs=`: `default`, or the `--set` overrides on top of it."""
    return "default" + "".join(f"+{s}" for s in args.sets)


class _ServerSQLite:
    """`--database sqlite`: no database process; the Prefect server keeps its SQLite file in
    its PREFECT_HOME (`LocalServer` with no URL)."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        pass

    def pid(self) -> int:
        return -1


def _database(args: argparse.Namespace) -> Any:
    """`--database`: a throwaway PostgreSQL (`LocalPostgres`: `with` gives its URL), or the
    server's own SQLite."""
    from embody.flows.postgres import LocalPostgres

    return _ServerSQLite() if args.database == "sqlite" else LocalPostgres()


def _full_cmd(data: Path, store: str, name: str, address: str, workers: int, batch: int,
              extra: list[str] = (), sets: list[str] = ()) -> list[str]:
    return [*EMBODY, "run", str(data), "--store", store, "--name", name,
            "--runner", "dask", "--dask-address", address, "--workers", str(workers),
            "--batch-size", str(batch), "--set", "run.report=false", "--no-progress", "--json",
            *[a for s in sets for a in ("--set", s)], *extra]


def full_run(args: argparse.Namespace, work: Path) -> None:
    """The production-shaped run (`--full`): see the module docstring."""
    import httpx

    from embody.flows.cluster import DaskProcesses
    from embody.flows.server import LocalServer
    from embody.store import ArtifactStore
    from embody.synth import default_dataset

    t_data = time.perf_counter()
    data = default_dataset(work / "data", n=args.n, seed=0)
    print(f"dataset: {args.n} default synthetic sequences in {time.perf_counter() - t_data:.0f} s "
          f"({data})", flush=True)
    store = args.store_url or str(work / "store-full")
    pg = _database(args)
    with S3Counter(store, work) as s3, pg as db_url:
        server = LocalServer(work / "prefect-home", database_url=db_url)
        with server as api:
            print(f"prefect server {api} on {args.database} ({db_url or 'PREFECT_HOME'})",
                  flush=True)
            cluster = DaskProcesses(work / "cluster", args.workers)
            with cluster as address:
                print(f"dask scheduler {address}, {args.workers} workers; worker threads: "
                      f"{json.dumps(cluster.thread_counts())}", flush=True)
                requests0 = s3.requests()
                r = drive("full", _full_cmd(data, store, "full", address, args.workers,
                                            args.batch_size, sets=args.sets),
                          _full_env(api, work), work, cluster, server.proc.pid, pg.pid())
                requests = s3.requests()
            errors = r["errors"] + _log_errors(work / "prefect-home" / "server.log")
            flow_runs = httpx.post(api + "/flow_runs/filter", json={}, timeout=60).json()
            per_run = [int(httpx.post(api + "/task_runs/count", json={
                "flow_runs": {"id": {"any_": [fr["id"]]}}}, timeout=60).json())
                for fr in flow_runs]
            summary, wall, n = r["summary"], r["wall_s"], args.n
            rows = [x for x in ArtifactStore(store).computations() if x["time"] >= r["started"]]
            files, size = store_size(store)
    done = [x["time"] for x in rows if x["step"] == "metrics"]
    span = (max(done) - min(x["time"] for x in rows)) if len(done) > 1 else None
    compute: dict[str, float] = {}
    for x in rows:
        compute[x["step"]] = compute.get(x["step"], 0.0) + float(x.get("compute_s") or 0.0)
    rate = 60 * n / wall
    steady = 60 * len(done) / span if span else rate
    print("compute seconds per sequence (summed over workers): " + " ".join(
        f"{k}={v / n:.2f}" for k, v in sorted(compute.items())), flush=True)
    median_s, shared_s = warm_compute(rows)
    # hours for N sequences at the warm per-sequence compute, W workers busy, plus the shared fit
    hours = {m: (m * median_s / args.workers + shared_s) / 3600 for m in (1000, 20000)}
    print(f"projection at {median_s:.1f} warm compute-s per sequence on {args.workers} "
          f"workers: {hours[1000]:.1f} h for 1,000 sequences, {hours[20000]:.1f} h for 20,000; "
          f"at this run's steady rate ({steady:.2f} seq/min): {1000 / steady / 60:.1f} h and "
          f"{20000 / steady / 60:.1f} h", flush=True)
    req = (f"store_requests_per_seq={(requests - requests0) / n:.1f} "
           if requests is not None else "")
    print(f"RESULT mode=full sequences={n} ok={summary.get('ok')} wall_s={wall:.1f} "
          f"seq_per_min={rate:.2f} steady_seq_per_min={steady:.2f} "
          f"peak_driver_rss_mb={r['peak_driver'] / 2**20:.0f} "
          f"peak_worker_rss_mb={r['peak_worker'] / 2**20:.0f} "
          f"api_errors={errors} store_files_per_seq={files / n:.1f} "
          f"store_mb_per_seq={size / n / 2**20:.2f} {req}"
          f"compute_s_per_seq={sum(compute.values()) / n:.2f} "
          f"worker_cpu_s_per_seq={r['worker_cpu_s'] / n:.2f} "
          f"max_task_runs_per_flow_run={max(per_run, default=0)} flow_runs={len(flow_runs)} "
          f"warm_compute_s_per_seq={median_s:.2f} projected_h_1000={hours[1000]:.1f} "
          f"projected_h_20k={hours[20000]:.1f} "
          f"workers={args.workers} batch={args.batch_size} database={args.database} "
          f"store={'local' if '://' not in store else store.split('://')[0]} "
          f"render={_render(args)} configs={_configs(args)} load_avg={r['load_avg']:.1f}",
          flush=True)


def _log_errors(path: Path) -> int:
    if not path.is_file():
        return 0
    return sum(bool(_ERRORS.search(line)) for line in
               path.read_text(errors="replace").splitlines())


def compare_workers(args: argparse.Namespace, work: Path) -> None:
    """`--full --compare-workers`: 1 and 2 single-threaded Dask workers on the same default-
    config sequences. A warm-up run (1 worker, 1 sequence) computes the shared shape fit and
    fills numba's kernel cache; then `2 × --rounds` chunks in the order 2,1,1,2,… (ABBA, so a
    load change hits both alike), each on a fresh cluster of that many workers and a fresh
    store holding only the warm-up's shape fit, so every chunk computes the same `--chunk`
    sequences. Rates are taken over the steady spans (first computed artifact → last
    metrics); the per-sequence CPU seconds of the workers, the driver, the scheduler and the
    Prefect server say where time went whatever the machine's load."""
    from embody.flows.cluster import DaskProcesses
    from embody.flows.server import LocalServer
    from embody.store import ArtifactStore
    from embody.synth import default_dataset

    size = args.chunk or 8
    data = default_dataset(work / "data", n=size, seed=0)
    order = [w for r in range(args.rounds) for w in ((2, 1) if r % 2 == 0 else (1, 2))]
    runs: list[dict[str, Any]] = []
    pg = _database(args)
    with pg as db_url:
        server = LocalServer(work / "prefect-home", database_url=db_url)
        with server as api:
            env = _full_env(api, work)
            print(f"prefect server {api} on {args.database}; {size} sequences per chunk, batch "
                  f"{args.batch_size}, order {order}", flush=True)
            warm_store = work / "store-warm"
            cluster = DaskProcesses(work / "cluster-warm", 1)
            with cluster as address:
                print(f"worker threads: {json.dumps(cluster.thread_counts())}", flush=True)
                warm = drive("warmup", _full_cmd(data, str(warm_store), "warm", address, 1, 1,
                                                 ["--limit", "1"], args.sets),
                             env, work, cluster, server.proc.pid, pg.pid())
            print(f"warm-up (shape fit, kernel caches): {warm['wall_s']:.0f} s", flush=True)
            for i, workers in enumerate(order):
                store = work / f"store-c{i}"
                shutil.copytree(warm_store / "artifacts" / "shape_fit",
                                store / "artifacts" / "shape_fit")
                cluster = DaskProcesses(work / f"cluster-c{i}", workers)
                with cluster as address:
                    r = drive(f"chunk{i}_{workers}w", _full_cmd(
                        data, str(store), f"c{i}", address, workers, args.batch_size,
                        sets=args.sets),
                        env, work, cluster, server.proc.pid, pg.pid())
                rows = ArtifactStore(store).computations()
                done = [x["time"] for x in rows if x["step"] == "metrics"]
                r.update(workers=workers, n=size, ok=r["summary"].get("ok"),
                         compute_s=sum(float(x.get("compute_s") or 0.0) for x in rows),
                         step_cpu_s=sum(float(x.get("cpu_s") or 0.0) for x in rows),
                         done=len(done), span_s=max(done) - min(x["time"] for x in rows)
                         if len(done) > 1 else None)
                r.pop("summary")
                runs.append(r)
                print(json.dumps({k: round(v, 2) if isinstance(v, float) else v
                                  for k, v in r.items()}), flush=True)
            errors = sum(r["errors"] for r in runs) + _log_errors(server.log_path)
    fig: dict[int, dict[str, float]] = {}
    for w in (1, 2):
        mine = [r for r in runs if r["workers"] == w and r["span_s"]]
        n = sum(r["n"] for r in mine)
        span = sum(r["span_s"] for r in mine)
        fig[w] = {"steady": 60 * sum(r["done"] for r in mine) / span,
                  "wall": 60 * n / sum(r["wall_s"] for r in mine),
                  "load": sum(r["load_avg"] for r in mine) / len(mine),
                  "worker_cpu": sum(r["worker_cpu_s"] for r in mine) / n,
                  "compute": sum(r["compute_s"] for r in mine) / n,
                  # CPU seconds of the steps' own compute threads: the load-independent cost
                  "step_cpu": sum(r["step_cpu_s"] for r in mine) / n,
                  "driver_cpu": sum(r["driver_cpu_s"] for r in mine) / n,
                  "server_cpu": sum(r["server_cpu_s"] for r in mine) / n,
                  "database_cpu": sum(r["database_cpu_s"] for r in mine) / n,
                  "scheduler_cpu": sum(r["scheduler_cpu_s"] for r in mine) / n,
                  # the share of the workers' wall time spent in a step's compute
                  "busy": sum(r["compute_s"] for r in mine) / (span * w),
                  "ok": sum(r["ok"] or 0 for r in mine), "n": n}
    one, two = fig[1], fig[2]
    print("per sequence, 1 worker / 2 workers: " + "; ".join(
        f"{k} {one[k]:.2f} / {two[k]:.2f}" for k in
        ("worker_cpu", "step_cpu", "compute", "driver_cpu", "server_cpu", "database_cpu",
         "scheduler_cpu", "busy")),
        flush=True)
    print(f"RESULT mode=full_compare chunks={len(runs)} chunk={size} "
          f"order={''.join(map(str, order))} "
          f"ok={one['ok'] + two['ok']}/{one['n'] + two['n']} "
          f"seq_per_min_1w={one['steady']:.3f} seq_per_min_2w={two['steady']:.3f} "
          f"ratio_2w_1w={two['steady'] / one['steady']:.2f} "
          f"wall_ratio_2w_1w={two['wall'] / one['wall']:.2f} "
          f"worker_cpu_s_per_seq_1w={one['worker_cpu']:.1f} "
          f"worker_cpu_s_per_seq_2w={two['worker_cpu']:.1f} "
          f"cpu_ratio_2w_1w={two['worker_cpu'] / one['worker_cpu']:.2f} "
          f"step_cpu_s_per_seq_1w={one['step_cpu']:.1f} "
          f"step_cpu_s_per_seq_2w={two['step_cpu']:.1f} "
          f"server_cpu_s_per_seq={(one['server_cpu'] + two['server_cpu']) / 2:.2f} "
          f"scheduler_cpu_s_per_seq={(one['scheduler_cpu'] + two['scheduler_cpu']) / 2:.2f} "
          f"database_cpu_s_per_seq={(one['database_cpu'] + two['database_cpu']) / 2:.2f} "
          f"driver_cpu_s_per_seq={(one['driver_cpu'] + two['driver_cpu']) / 2:.2f} "
          f"busy_1w={one['busy']:.2f} busy_2w={two['busy']:.2f} "
          f"load_1w={one['load']:.1f} load_2w={two['load']:.1f} api_errors={errors} "
          f"batch={args.batch_size} database={args.database} store=local render={_render(args)} "
          f"configs={_configs(args)}",
          flush=True)


def interleaved(b: Bench, size: int, rounds: int) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """1 and 2 workers on alternating chunks of `size` fresh sequences (order ABBA, so a load
    change during the measurement hits both alike); rates over the steady spans."""
    offset = 0
    runs: list[dict[str, Any]] = []
    store = b.work / "store-r"
    # The shared shape fit (a hit for every chunk, as in a long run): copied from the cold run.
    shutil.copytree(b.work / "store-a" / "artifacts" / "shape_fit",
                    store / "artifacts" / "shape_fit", dirs_exist_ok=True)
    for r in range(rounds):
        for workers in ((2, 1) if r % 2 == 0 else (1, 2)):
            runs.append(b.run(f"chunk{r}_{workers}w", store, "processes",
                              workers, n=size, offset=offset))
            offset = (offset + size) % b.args.n
    rates: dict[str, float] = {}
    for w in (1, 2):
        mine = [x for x in runs if x["workers"] == w and x["steady_span_s"]]
        done, span = sum(x["steady_done"] for x in mine), sum(x["steady_span_s"] for x in mine)
        rates[f"{w}w"] = round(60 * done / span, 2) if span else float("nan")
        rates[f"{w}w_wall"] = round(60 * sum(x["n"] for x in runs if x["workers"] == w)
                                    / sum(x["wall_s"] for x in runs if x["workers"] == w), 2)
        rates[f"{w}w_load"] = round(sum(x["load_avg"] for x in mine) / max(1, len(mine)), 1)
        rates[f"{w}w_worker_cpu_s_per_seq"] = round(
            sum(x["worker_cpu_s"] for x in mine) / max(1, sum(x["n"] for x in mine)), 3)
        rates[f"{w}w_compute_s_per_seq"] = round(
            sum(x["compute_s"] for x in mine) / max(1, sum(x["n"] for x in mine)), 3)
    return rates, runs


def kill_resume(b: Bench, n: int) -> tuple[int, int]:
    """SIGKILL a cold run of `n` sequences at half, rerun it: (recomputed, unfinished at kill)."""
    from embody.store import ArtifactStore, Manifest
    store_d = b.work / "store-d"
    killed = b.run("killed", store_d, "processes", b.args.workers, n=n, kill_at=max(1, n // 2))
    st = ArtifactStore(store_d)
    at_kill = {(s, k) for s, k, _ in st.entries()}
    before = len(st.computations())
    resumed = b.run("resumed", store_d, "processes", b.args.workers, n=n)
    recomputed = len(st.computations()) - before
    needed = Manifest.load(st, "scale").keys()
    unfinished = len(needed - at_kill)
    print(f"kill: {len(at_kill)} artifacts in the store at the kill "
          f"(after {killed['wall_s']} s), {len(needed)} in the finished run; "
          f"resume computed {recomputed} ({resumed['computed']})", flush=True)
    return recomputed, unfinished


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--n-small", type=int, default=200,
                        help="Sequences of the kill/resume and Dask phases (N for both costs "
                             "hours on a shared 2-core machine).")
    parser.add_argument("--full", action="store_true",
                        help="The production-shaped run: default configs and lengths, render on, "
                             "a dask scheduler and workers, Prefect on PostgreSQL (hours at "
                             "N=1000 on 2 cores).")
    parser.add_argument("--store-url", default=None,
                        help="--full: the store (a folder or URL; default a folder in --out).")
    parser.add_argument("--compare-workers", action="store_true",
                        help="--full: 1 vs 2 Dask workers on interleaved chunks (order 2,1,1,2) "
                             "instead of the N-sequence run.")
    parser.add_argument("--chunk", type=int, default=None,
                        help="Sequences per chunk of the 1-vs-2-worker comparison (default 64; "
                             "--full --compare-workers: 8).")
    parser.add_argument("--rounds", type=int, default=2,
                        help="Rounds of the interleaved phase (each: one 1- and one 2-worker chunk).")
    parser.add_argument("--database", choices=("postgresql", "sqlite"), default="postgresql",
                        help="--full: the Prefect server's database (sqlite: its own file, where "
                             "no PostgreSQL can run).")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                        help="--full: a config override for every `embody run` (repeatable); "
                             "the RESULT line's configs= lists it.")
    parser.add_argument("--skip", default="", help="Comma-separated phases to skip: "
                        "warm,dask,ratio,kill (development only).")
    parser.add_argument("--out", type=Path, default=None, help="Work folder (default: a temp dir).")
    args = parser.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    work = (args.out or Path(tempfile.mkdtemp(prefix="embody-scale-"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    for old in work.glob("store-*"):
        shutil.rmtree(old, ignore_errors=True)
    if args.full:
        shutil.rmtree(work / "prefect-home", ignore_errors=True)
        what = (f"1 vs 2 dask workers on {2 * args.rounds} chunks of {args.chunk or 8}"
                if args.compare_workers else f"{args.n} sequences on {args.workers} dask workers")
        print(f"scale --full: {what}; default synthetic sequences (default lengths and configs, "
              f"render on, report off), batch {args.batch_size}; {os.cpu_count()} CPUs, load "
              f"{os.getloadavg()[0]:.1f}; work {work}", flush=True)
        if args.compare_workers:
            compare_workers(args, work)
        else:
            full_run(args, work)
        return
    print(f"scale: {args.n} synthetic sequences of {args.frames} frames, batch {args.batch_size}, "
          f"{args.workers} workers; render OFF, end-of-run report OFF; "
          + "stage configs cheap (orchestration-bound): " + " ".join(CHEAP[1::2])
          + f"; {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}; work {work}", flush=True)

    from embody.flows.server import LocalServer

    shutil.rmtree(work / "prefect-home", ignore_errors=True)
    server = LocalServer(work / "prefect-home")
    t0 = time.perf_counter()
    with server as api:
        print(f"prefect server {api} healthy after {time.perf_counter() - t0:.1f} s", flush=True)
        b = Bench(args, work, api, server)
        w = args.workers
        cold = b.run("cold_processes", work / "store-a", "processes", w)
        steps = step_seconds(work / "store-a", args.n)
        print("compute seconds per sequence (cold, summed over workers): "
              + " ".join(f"{k}={v}" for k, v in steps.items())
              + f" total={round(sum(steps.values()), 3)}", flush=True)
        warm = b.run("warm_processes", work / "store-a", "processes", w) \
            if "warm" not in skip else None
        small = min(args.n, args.n_small)
        recomputed = unfinished = -1
        if "kill" not in skip:
            try:
                recomputed, unfinished = kill_resume(b, small)
            except Exception as exc:  # report what was measured, not nothing
                print(f"kill phase failed: {type(exc).__name__}: {exc}", flush=True)
        rates: dict[str, float] = {}
        chunks: list[dict[str, Any]] = []
        if "ratio" not in skip:
            try:
                rates, chunks = interleaved(b, args.chunk or 64, args.rounds)
                print("interleaved 1 vs 2 workers (steady seq/min, wall seq/min, mean load): "
                      + json.dumps(rates), flush=True)
            except Exception as exc:
                print(f"ratio phase failed: {type(exc).__name__}: {exc}", flush=True)
        dask = None
        if "dask" not in skip:
            try:
                dask = b.run("cold_dask", work / "store-b", "dask", w, n=small)
            except Exception as exc:
                print(f"dask phase failed: {type(exc).__name__}: {exc}", flush=True)
        mem = [r for r in (cold, dask, *chunks) if r]
        server_rss = 0
        try:
            import psutil
            p = psutil.Process(server.proc.pid)
            server_rss = max([p.memory_info().rss] +
                             [c.memory_info().rss for c in p.children(recursive=True)])
        except Exception:
            pass
        print(f"prefect server RSS now {server_rss / 2**20:.0f} MB; task runs per cold run "
              f"{cold['task_runs']} ({cold['task_runs'] / args.n:.2f} per sequence); driver CPU "
              f"{cold['driver_cpu_s']} s, server CPU {cold['server_cpu_s']} s "
              f"({1000 * (cold['driver_cpu_s'] + cold['server_cpu_s']) / max(1, cold['task_runs']):.0f}"
              f" ms per task run)", flush=True)
    ratio = rates.get("2w", float("nan")) / rates.get("1w", float("nan")) if rates else float("nan")
    print(f"RESULT sequences={args.n} seq_per_min={cold['seq_per_min']} "
          f"seq_per_min_1worker={rates.get('1w', 'nan')} "
          f"peak_driver_rss_mb={max(r['peak_driver_rss_mb'] for r in mem)} "
          f"peak_worker_rss_mb={max(r['peak_worker_rss_mb'] for r in mem)} "
          f"warm_s={warm['wall_s'] if warm else 'nan'} resumed_recomputed={recomputed} "
          f"unfinished_at_kill={unfinished} api_errors={b.errors} "
          f"seq_per_min_dask={dask['seq_per_min'] if dask else 'nan'} "
          f"steady_seq_per_min_dask={dask['steady_seq_per_min'] if dask else 'nan'} "
          f"n_kill_dask={small} "
          f"steady_seq_per_min={cold['steady_seq_per_min']} "
          f"seq_per_min_2worker_chunks={rates.get('2w', 'nan')} ratio_2w_1w={ratio:.2f} "
          f"load_avg={cold['load_avg']} task_runs={cold['task_runs']} "
          f"driver_cpu_ms_per_task_run={1000 * cold['driver_cpu_s'] / max(1, cold['task_runs']):.0f} "
          f"compute_s_per_seq={round(sum(steps.values()), 3)} batch={args.batch_size} "
          f"render=off frames={args.frames} configs=cheap")


if __name__ == "__main__":
    main()
