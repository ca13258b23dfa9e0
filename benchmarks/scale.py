"""Dataset-scale benchmark: N short synthetic sequences through `embody run` on a real Prefect server.

Every run is a separate `embody run` process (the default pipeline: source → collide →
shape_fit → retarget → refine (geometric critic) → metrics) pointed at one persistent
`prefect server start` (its own PREFECT_HOME, SQLite), sampled with psutil every 0.2 s:

1. cold, `--runner processes`, W workers       → seq_per_min, driver / worker peak RSS, task runs
2. warm rerun of (1)                            → warm_s (every step a store hit)
3. cold, `--runner dask` (LocalCluster, W workers) → seq_per_min_dask
4. cold, `--runner processes`, 1 worker         → seq_per_min_1worker
5. cold (processes, W workers) killed with SIGKILL (driver and workers) once half the sequences
   have their metrics, then rerun: resumed_recomputed (artifacts computed by the rerun) against
   unfinished_at_kill (artifacts of the finished run that were not in the store at the kill).

Made cheap per sequence through config only, and said so in the output: rendering off
(`--no-render`; benchmarks/render.py measures it), no end-of-run report (`run.report=false`;
benchmarks/report.py measures it), sequences cropped to `--frames` (default 60). Collision,
IK and the critic keep their defaults unless `--cheap` (one IK iteration, short shape fit, one
critic round, collision optimisation off) — for developing the script, not for the figures.
`api_errors` counts 5xx / "database is locked" / tracebacks in the server log and in the runs'
stderr. Peak RSS: the driver process alone; workers: the largest child process (Prefect
process-pool workers, Dask nanny/worker processes).

    python benchmarks/scale.py [--n 1000] [--frames 60] [--workers 2] [--batch-size 8] [--out DIR]
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

#: Development only: the real steps with minimal work.
CHEAP = ["--set", "collision.enabled=false", "--set", "ik.iterations=1",
         "--set", "ik.shape_iterations=10", "--set", "critic.rounds=1"]
_ERRORS = re.compile(r"database is locked|HTTPStatusError|Service Unavailable|Internal Server Error"
                     r"|OperationalError|Traceback|\b50[0-9] ", re.I)
EMBODY = [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())"]


def write_dataset(folder: Path, n: int, frames: int, seed: int = 0) -> Path:
    """`n` synthetic sequences (embody.synth) cropped to `frames`; reused when already there."""
    done = folder / ".complete"
    if done.is_file():
        return folder
    from embody.io import save
    from embody.synth.generator import generate_sequence
    from embody.synth.kinematics import ArmIK

    folder.mkdir(parents=True, exist_ok=True)
    ik = ArmIK()
    for i in range(n):
        m = generate_sequence(seed, i, ik)
        f = min(frames, m.num_frames)
        save(replace(m, pose=m.pose[:f], transl=m.transl[:f]), folder / f"seq_{i:05d}.npz")
    done.write_text("ok")
    return folder


def _tree_rss(proc: Any) -> tuple[int, int]:
    """(driver RSS, largest child RSS) in bytes."""
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


class Bench:
    def __init__(self, args: argparse.Namespace, work: Path, api: str, server_log: Path) -> None:
        self.args, self.work, self.api, self.server_log = args, work, api, server_log
        self.data = write_dataset(work / f"data-n{args.n}-f{args.frames}", args.n, args.frames)
        self.env = dict(os.environ, PREFECT_API_URL=api, PYTHONPATH=str(ROOT), DO_NOT_TRACK="1",
                        PREFECT_SERVER_ANALYTICS_ENABLED="false", OMP_NUM_THREADS="1",
                        MKL_NUM_THREADS="1")
        self.errors = 0

    def command(self, store: Path, runner: str, workers: int) -> list[str]:
        a = self.args
        return [*EMBODY, "run", str(self.data), "--store", str(store), "--name", "scale",
                "--runner", runner, "--workers", str(workers), "--batch-size", str(a.batch_size),
                "--no-render", "--set", "run.report=false", "--no-progress", "--json",
                *(CHEAP if a.cheap else [])]

    def run(self, label: str, store: Path, runner: str, workers: int,
            kill_at: int | None = None) -> dict[str, Any]:
        """One `embody run`, sampled; `kill_at`: SIGKILL its group once that many sequences
        have their metrics artifact."""
        import psutil
        from embody.store import ArtifactStore

        log_before = self.server_log.stat().st_size if self.server_log.is_file() else 0
        tasks_before = count_task_runs(self.api)
        err_path = self.work / f"{label}.stderr"
        t0, started = time.perf_counter(), time.time()
        with open(err_path, "w") as err:
            proc = subprocess.Popen(self.command(store, runner, workers), env=self.env,
                                    cwd=self.work, stdout=subprocess.PIPE, stderr=err, text=True,
                                    start_new_session=True)
            ps = psutil.Process(proc.pid)
            peak_driver = peak_worker = 0
            killed = False
            metrics = store / "counters" / "metrics.jsonl"
            try:
                while proc.poll() is None:
                    d, w = _tree_rss(ps)
                    peak_driver, peak_worker = max(peak_driver, d), max(peak_worker, w)
                    if kill_at is not None and metrics.is_file() and \
                            sum(1 for _ in metrics.open()) >= kill_at:
                        os.killpg(proc.pid, signal.SIGKILL)
                        killed = True
                        break
                    time.sleep(0.2)
                out = proc.communicate()[0]
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
        rows = [r for r in ArtifactStore(store).computations() if r["time"] >= started]
        done = [r["time"] for r in rows if r["step"] == "metrics"]
        # Sequences per minute from the first computed artifact to the last finished sequence:
        # the rate without process start-up (imports, worker spawn), which N does not change.
        steady = (60 * len(done) / (max(done) - min(r["time"] for r in rows))
                  if len(done) > 2 else None)
        n = self.args.n
        res = {"label": label, "wall_s": round(wall, 2), "seq_per_min": round(60 * n / wall, 2),
               "steady_seq_per_min": round(steady, 2) if steady else None,
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--cheap", action="store_true",
                        help="Minimal collision/IK/critic work (developing the script only).")
    parser.add_argument("--skip", default="", help="Comma-separated phases to skip: "
                        "dask,one,kill (development only).")
    parser.add_argument("--out", type=Path, default=None, help="Work folder (default: a temp dir).")
    args = parser.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    work = (args.out or Path(tempfile.mkdtemp(prefix="embody-scale-"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    for old in work.glob("store-*"):
        shutil.rmtree(old, ignore_errors=True)
    print(f"scale: {args.n} synthetic sequences of {args.frames} frames, batch {args.batch_size}, "
          f"{args.workers} workers; render OFF, end-of-run report OFF"
          f"{', CHEAP stage config (not for figures)' if args.cheap else ', stage configs default'}"
          f"; work {work}", flush=True)

    from embody.flows.server import LocalServer

    shutil.rmtree(work / "prefect-home", ignore_errors=True)
    server = LocalServer(work / "prefect-home")
    t0 = time.perf_counter()
    with server as api:
        print(f"prefect server {api} healthy after {time.perf_counter() - t0:.1f} s", flush=True)
        b = Bench(args, work, api, server.log_path)
        w = args.workers
        cold = b.run("cold_processes", work / "store-a", "processes", w)
        steps = step_seconds(work / "store-a", args.n)
        print("compute seconds per sequence (cold, summed over workers): "
              + " ".join(f"{k}={v}" for k, v in steps.items())
              + f" total={round(sum(steps.values()), 2)}", flush=True)
        warm = b.run("warm_processes", work / "store-a", "processes", w)
        dask = b.run("cold_dask", work / "store-b", "dask", w) if "dask" not in skip else None
        one = b.run("cold_1worker", work / "store-c", "processes", 1) if "one" not in skip else None
        recomputed = unfinished = -1
        if "kill" not in skip:
            from embody.store import ArtifactStore, Manifest
            store_d = work / "store-d"
            killed = b.run("killed", store_d, "processes", w, kill_at=max(1, args.n // 2))
            st = ArtifactStore(store_d)
            at_kill = {(s, k) for s, k, _ in st.entries()}
            before = len(st.computations())
            resumed = b.run("resumed", store_d, "processes", w)
            recomputed = len(st.computations()) - before
            needed = Manifest.load(st, "scale").keys()
            unfinished = len(needed - at_kill)
            print(f"kill: {len(at_kill)} artifacts in the store at the kill "
                  f"(after {killed['wall_s']} s), {len(needed)} in the finished run; "
                  f"resume computed {recomputed} ({resumed['computed']})", flush=True)
        mem = [r for r in (cold, dask, one) if r]
        server_rss = 0
        try:
            import psutil
            p = psutil.Process(server.proc.pid)
            server_rss = max([p.memory_info().rss] +
                             [c.memory_info().rss for c in p.children(recursive=True)])
        except Exception:
            pass
        print(f"prefect server RSS now {server_rss / 2**20:.0f} MB; task runs per cold run "
              f"{cold['task_runs']} ({cold['task_runs'] / args.n:.2f} per sequence)", flush=True)
    print(f"RESULT sequences={args.n} seq_per_min={cold['seq_per_min']} "
          f"seq_per_min_1worker={one['seq_per_min'] if one else 'nan'} "
          f"peak_driver_rss_mb={max(r['peak_driver_rss_mb'] for r in mem)} "
          f"peak_worker_rss_mb={max(r['peak_worker_rss_mb'] for r in mem)} "
          f"warm_s={warm['wall_s']} resumed_recomputed={recomputed} "
          f"unfinished_at_kill={unfinished} api_errors={b.errors} "
          f"seq_per_min_dask={dask['seq_per_min'] if dask else 'nan'} "
          f"steady_seq_per_min={cold['steady_seq_per_min']} "
          f"steady_seq_per_min_1worker={one['steady_seq_per_min'] if one else 'nan'} "
          f"task_runs={cold['task_runs']} compute_s_per_seq={round(sum(steps.values()), 2)} "
          f"render=off frames={args.frames}{' cheap=1' if args.cheap else ''}")


if __name__ == "__main__":
    main()
