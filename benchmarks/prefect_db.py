"""Prefect's database under concurrent writers: SQLite against PostgreSQL.

For each backend a real `prefect server start` (SQLite in its PREFECT_HOME, or a throwaway
PostgreSQL 15 from `embody.flows.postgres`) and, for W in (2, 8), W writer processes started
together (they wait on a file after their imports), each running a flow of `--tasks` task
runs on a 4-thread pool: W × 4 clients creating task runs and setting their states at once,
as a cluster's workers do. Counted per backend and W:

- `errors`: "database is locked"-class failures: the server log's 5xx / `database is locked` /
  `OperationalError` / traceback lines plus the writers' (scripts/scale.py's pattern), and
  writers that failed (Prefect's client retries a 503 quietly, so the log is the witness);
- `lost`: task runs not recorded COMPLETED (the API's count against W × tasks) once the
  server's event pipeline has settled (up to 30 s without progress after the writers exit);
- `task_runs_per_s`: recorded task runs per second, from the start until they are all recorded.

    python benchmarks/prefect_db.py [--tasks 40] [--writers 2,8] [--backends sqlite,postgres]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

_ERRORS = re.compile(r"database is locked|HTTPStatusError|Service Unavailable|Internal Server Error"
                     r"|OperationalError|Traceback|HTTP/\d(?:\.\d)?\" 5\d\d|status(?: code)? 5\d\d",
                     re.I)

_WRITER = """
import sys, time
from pathlib import Path
from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.task_runners import ThreadPoolTaskRunner

@task(persist_result=False, cache_policy=NO_CACHE)
def write(i: int) -> int:
    return i

@flow(name="db-writer", persist_result=False, task_runner=ThreadPoolTaskRunner(max_workers=4))
def writer(n: int) -> int:
    return sum(f.result() for f in [write.submit(i) for i in range(n)])

go, n = Path(sys.argv[1]), int(sys.argv[2])
while not go.exists():
    time.sleep(0.01)
assert writer(n) == n * (n - 1) // 2
"""


def _count(api: str, flow_name: str, state: str | None = None) -> int:
    import httpx
    body: dict = {"flows": {"name": {"any_": [flow_name]}}}
    if state:
        body["task_runs"] = {"state": {"type": {"any_": [state]}}}
    r = httpx.post(api + "/task_runs/count", json=body, timeout=60)
    r.raise_for_status()
    return int(r.json())


def phase(api: str, log: Path, work: Path, writers: int, tasks: int) -> dict[str, float]:
    """`writers` processes at once; errors, lost task runs and throughput."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_API_URL=api, PREFECT_HOME=str(work / "client"), DO_NOT_TRACK="1",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="WARNING")
    go = work / f"go-{writers}"
    go.unlink(missing_ok=True)
    done_before = _count(api, "db-writer", "COMPLETED")
    log_before = log.stat().st_size if log.is_file() else 0
    errs = [work / f"writer-{writers}-{i}.err" for i in range(writers)]
    procs = []
    for path in errs:
        with open(path, "w") as err:
            procs.append(subprocess.Popen([sys.executable, "-c", _WRITER, str(go), str(tasks)],
                                          env=env, stdout=err, stderr=subprocess.STDOUT))
    time.sleep(max(3.0, 1.5 * writers))  # their imports (~2-3 s each), then all start at once
    t0 = time.perf_counter()
    go.write_text("go")
    codes = [p.wait() for p in procs]
    writers_s = time.perf_counter() - t0
    # Task-run states reach the database through the server's event pipeline, after the
    # writers exit: wait until every task run is recorded, or nothing moves for 30 s.
    expected, seen, moved = writers * tasks, -1, time.perf_counter()
    while time.perf_counter() - moved < 30 and time.perf_counter() - t0 < 600:
        done = _count(api, "db-writer", "COMPLETED") - done_before
        if done >= expected:
            break
        if done != seen:
            seen, moved = done, time.perf_counter()
        time.sleep(0.5)
    wall = time.perf_counter() - t0
    text = ""
    if log.is_file():
        with open(log, "rb") as f:
            f.seek(log_before)
            text = f.read().decode(errors="replace")
    text += "".join(p.read_text(errors="replace") for p in errs)
    errors = sum(bool(_ERRORS.search(line)) for line in text.splitlines())
    locked = sum("database is locked" in line.lower() for line in text.splitlines())
    done = _count(api, "db-writer", "COMPLETED") - done_before
    return {"errors": errors + sum(c != 0 for c in codes), "locked": locked,
            "failed_writers": sum(c != 0 for c in codes), "lost": writers * tasks - done,
            "task_runs_per_s": round(done / wall, 1), "wall_s": round(wall, 1),
            "writers_s": round(writers_s, 1), "settle_s": round(wall - writers_s, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", type=int, default=40, help="Task runs per writer.")
    parser.add_argument("--writers", default="2,8")
    parser.add_argument("--backends", default="sqlite,postgres")
    args = parser.parse_args()
    counts = [int(w) for w in args.writers.split(",")]
    from embody.flows.postgres import LocalPostgres
    from embody.flows.server import LocalServer

    print(f"prefect_db: writers {counts}, {args.tasks} task runs each on 4 threads; "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}", flush=True)
    results: dict[str, dict[int, dict[str, float]]] = {}
    for backend in args.backends.split(","):
        work = Path(tempfile.mkdtemp(prefix=f"embody-db-{backend}-"))
        pg = LocalPostgres() if backend == "postgres" else None
        try:
            url = pg.start() if pg else None
            server = LocalServer(work / "home", database_url=url)
            with server as api:
                results[backend] = {}
                for w in counts:
                    r = phase(api, server.log_path, work, w, args.tasks)
                    results[backend][w] = r
                    print(f"{backend} writers={w}: {r}", flush=True)
        finally:
            if pg is not None:
                pg.stop()
    fields = []
    for backend, by_w in results.items():
        short = "pg" if backend == "postgres" else backend
        for w, r in by_w.items():
            fields += [f"{short}_errors_{w}w={r['errors']}", f"{short}_locked_{w}w={r['locked']}",
                       f"{short}_lost_{w}w={r['lost']}",
                       f"{short}_task_runs_per_s_{w}w={r['task_runs_per_s']}"]
    print("RESULT " + " ".join(fields) + f" tasks_per_writer={args.tasks} "
          f"load_avg={os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
