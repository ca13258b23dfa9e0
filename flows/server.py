"""A persistent local Prefect server (`prefect server start`) as a child process.

Schedules only fire on a persistent server, and big runs want one outside the driver. Used by
`benchmarks/scale.py` and the real-server test; users run `prefect server start` themselves.
The server gets its own `PREFECT_HOME` (SQLite database there, or `database_url`: PostgreSQL,
the production configuration, see `flows.postgres`), listens on loopback only, and is offline
(no telemetry, no UI).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

__all__ = ["LocalServer", "free_port"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LocalServer:
    """`with LocalServer(home) as api_url:` runs a server until the block ends (even on error)."""

    def __init__(self, home: str | Path, port: int | None = None, log: str | Path | None = None,
                 startup_timeout_s: float = 240.0, database_url: str | None = None) -> None:
        self.home = Path(home)
        self.database_url = database_url
        self.port = port or free_port()
        self.log_path = Path(log) if log else self.home / "server.log"
        self.startup_timeout_s = startup_timeout_s
        self.proc: subprocess.Popen | None = None
        self._log: IO[bytes] | None = None

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    def env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
        env.update(PREFECT_HOME=str(self.home), DO_NOT_TRACK="1",
                   PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_UI_ENABLED="false",
                   PREFECT_LOGGING_LEVEL="WARNING",
                   # Prefect's 5 s connect / 10 s statement defaults: on a loaded machine (load
                   # 33-41 on 2 cores) the server's own background services timed out on
                   # PostgreSQL 162 times in one run while every API call the run made succeeded.
                   PREFECT_SERVER_DATABASE_CONNECTION_TIMEOUT="30",
                   PREFECT_SERVER_DATABASE_TIMEOUT="30")
        if self.database_url:
            env["PREFECT_API_DATABASE_CONNECTION_URL"] = self.database_url
        return env

    def start(self) -> str:
        import httpx

        self.home.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1",
             "--port", str(self.port)],
            env=self.env(), stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + self.startup_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"prefect server exited ({self.proc.returncode}); see "
                                   f"{self.log_path}")
            try:
                if httpx.get(self.api_url + "/health", timeout=2).status_code == 200:
                    return self.api_url
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        self.stop()
        raise TimeoutError(f"prefect server not healthy after {self.startup_timeout_s:.0f} s")

    def stop(self) -> None:
        """SIGTERM to the server's process group, SIGKILL after 15 s."""
        if self.proc is not None and self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
            except ProcessLookupError:
                pass
        if self._log is not None:
            self._log.close()
            self._log = None

    def __enter__(self) -> str:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
