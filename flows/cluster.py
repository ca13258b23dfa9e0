"""A Dask cluster of separate processes, started from Dask's own command lines.

What a user runs on a cluster, on one machine: `dask scheduler` and `dask worker ADDRESS`
processes, each worker with its own working directory and temporary folder, sharing nothing
with the driver but the scheduler's address, the store and the Prefect API (which reaches the
workers inside each task's serialized context). Used by the cluster tests and
`benchmarks/scale.py --full`; `embody run --runner dask --dask-address ADDRESS` is the driver.
Workers run without a nanny, so one process is one worker: killing it loses that worker.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import IO, Any

from embody.flows.service import LocalService

__all__ = ["DASK_TICK", "DaskProcesses"]

#: Dask's event-loop tick (blocked-loop warnings) and system monitor (the dashboard's CPU and
#: memory plots) at intervals for a batch cluster rather than an interactive dashboard.
DASK_TICK = {"DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL": "1s",
             "DASK_DISTRIBUTED__ADMIN__SYSTEM_MONITOR__INTERVAL": "5s"}


def _dask() -> str:
    """The `dask` command of this interpreter's environment (else the one on PATH)."""
    local = Path(sys.executable).with_name("dask")
    return str(local) if local.is_file() else (shutil.which("dask") or "dask")


def _thread_counts(dask_worker: Any) -> dict[str, Any]:
    """Run inside a worker (`Client.run`): see `DaskProcesses.thread_counts`."""
    import numba
    import torch
    from threadpoolctl import threadpool_info

    return {"dask": dask_worker.state.nthreads, "torch": torch.get_num_threads(),
            "torch_interop": torch.get_num_interop_threads(), "numba": numba.get_num_threads(),
            "pools": sorted({f"{i['user_api']}:{i['num_threads']}" for i in threadpool_info()}),
            "profiler": "profile" in dask_worker.periodic_callbacks,
            "llvmpipe": os.environ.get("LP_NUM_THREADS"),
            "tick_ms": round(1000 * dask_worker._tick_interval),
            "monitor_ms": round(dask_worker.periodic_callbacks["monitor"].callback_time)}


class DaskProcesses(LocalService):
    """`with DaskProcesses(folder, workers=2) as address:` scheduler and workers until the block
    ends. `folder/scheduler`, `folder/worker-<i>/{cwd,tmp,dask}` hold each process's files."""

    def __init__(self, folder: str | Path, workers: int = 2, env: dict[str, str] | None = None,
                 startup_timeout_s: float = 120.0, preload: bool = True) -> None:
        self.folder = Path(folder)
        #: `--preload embody.flows.preload` (what embody's steps need, see there); tests of
        #: stand-in steps go without it
        self.preload = preload
        self.n_workers = workers
        self.extra_env = dict(env or {})
        self.startup_timeout_s = startup_timeout_s
        self.scheduler: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []
        self.killed: set[int] = set()
        self.address = ""
        self._logs: list[IO[bytes]] = []

    def _env(self, home: Path) -> dict[str, str]:
        """The parent's environment without its Prefect settings and temp folder: a worker
        gets its own `PREFECT_HOME` and `TMPDIR`; single-threaded BLAS, OpenMP and numba (one
        task per worker, `--nthreads 1`; `embody.flows.preload` also holds torch to one thread);
        the render's software GL (Mesa llvmpipe) rasterises on the task's own thread
        (`LP_NUM_THREADS=0`) instead of one thread per core. Dask's housekeeping runs less
        often (`DASK_TICK`): its 20 ms event-loop tick and 0.5 s system monitor cost an idle
        scheduler 3.3 % and each idle worker 3.2 % of a core (0.8-1.1 % and 1.2-1.9 % at these
        intervals), on the cores the workers compute on."""
        env = {k: v for k, v in os.environ.items()
               if not k.startswith(("PREFECT_", "DASK_")) and k not in ("TMPDIR", "TMP", "TEMP")}
        tmp = home / "tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        env.update(TMPDIR=str(tmp), PREFECT_HOME=str(home / "prefect"), DO_NOT_TRACK="1",
                   PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="WARNING",
                   OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   NUMBA_NUM_THREADS="1", NUMEXPR_NUM_THREADS="1", VECLIB_MAXIMUM_THREADS="1",
                   LP_NUM_THREADS="0", **DASK_TICK, **self.extra_env)
        return env

    def _spawn(self, args: list[str], home: Path, name: str) -> subprocess.Popen:
        cwd = home / "cwd"
        cwd.mkdir(parents=True, exist_ok=True)
        log = open(home / f"{name}.log", "ab")
        self._logs.append(log)
        return subprocess.Popen([_dask(), *args],
                                cwd=cwd, env=self._env(home), stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)

    def start(self) -> str:
        home = self.folder / "scheduler"
        info = home / "scheduler.json"
        info.unlink(missing_ok=True)
        self.scheduler = self._spawn(
            ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
             "--scheduler-file", str(info)], home, "scheduler")
        deadline = time.monotonic() + self.startup_timeout_s
        while not info.is_file() or not info.read_text().strip():
            self._check(self.scheduler, "scheduler", deadline)
            time.sleep(0.1)
        self.address = json.loads(info.read_text())["address"]
        for i in range(self.n_workers):
            self.add_worker()
        self.wait_for_workers(self.n_workers, deadline)
        return self.address

    def add_worker(self) -> subprocess.Popen:
        """Start one more `dask worker` (its own cwd, temp folder and Dask local directory)."""
        i = len(self.workers)
        home = self.folder / f"worker-{i}"
        proc = self._spawn(
            ["worker", self.address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
             "--name", f"w{i}", "--local-directory", str(home / "dask"),
             *(["--preload", "embody.flows.preload"] if self.preload else [])], home, "worker")
        self.workers.append(proc)
        return proc

    def wait_for_workers(self, n: int, deadline: float | None = None) -> None:
        from distributed import Client

        deadline = deadline or time.monotonic() + self.startup_timeout_s
        with Client(self.address, timeout=30) as client:
            while len(client.scheduler_info(n_workers=-1)["workers"]) < n:
                for i, w in enumerate(self.workers):
                    if w.poll() is None or i in self.killed:
                        continue
                    raise RuntimeError(f"dask worker {i} exited ({w.returncode}); see "
                                       f"{self.folder / f'worker-{i}' / 'worker.log'}")
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{n} dask workers not up within the timeout")
                time.sleep(0.2)

    def thread_counts(self) -> dict[str, dict[str, Any]]:
        """Per worker address, the threads its compute libraries would use: Dask's task
        threads, torch's intra- and inter-op pools, numba's, and every BLAS/OpenMP pool
        threadpoolctl finds. All 1 when the workers are single-threaded, as the benchmarks'
        worker counts assume (a second thread per worker would compete for the same cores).
        `profiler`: whether Dask's statistical profiler samples the worker's tasks; `tick_ms`
        and `monitor_ms`: its event-loop tick and system-monitor intervals (`DASK_TICK`)."""
        from distributed import Client

        with Client(self.address, timeout=30) as client:
            return client.run(_thread_counts)

    def _check(self, proc: subprocess.Popen, name: str, deadline: float) -> None:
        if proc.poll() is not None:
            raise RuntimeError(f"dask {name} exited ({proc.returncode}); see {self.folder}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"dask {name} not up within {self.startup_timeout_s:.0f} s")

    def kill_worker(self, i: int) -> None:
        """SIGKILL worker `i` (a crash: no goodbye to the scheduler)."""
        proc = self.workers[i]
        self.killed.add(i)
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()

    def stop(self) -> None:
        for proc in [*self.workers, self.scheduler]:
            if proc is None or proc.poll() is not None:
                continue
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            except ProcessLookupError:
                pass
        for log in self._logs:
            log.close()
        self._logs = []
