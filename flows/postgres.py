"""A throwaway PostgreSQL server (Debian's `postgresql` binaries) for Prefect's database.

Prefect's production database is PostgreSQL: SQLite answers "database is locked" once several
clients write at once. The tests and `benchmarks/` start one here, in a temporary folder, on a
free loopback port, with trust authentication and a socket in that folder, so nothing of the
machine's own PostgreSQL (if any) is touched. PostgreSQL refuses to run as root: as root the
server runs as the `postgres` system user (the package creates it), which owns the folder.
"""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from embody.flows.server import free_port
from embody.flows.service import LocalService

__all__ = ["LocalPostgres", "postgres_bin"]

_BIN_DIRS = ("/usr/lib/postgresql/{v}/bin",)
_VERSIONS = ("17", "16", "15", "14", "13")


def postgres_bin() -> Path | None:
    """The folder of `initdb`/`pg_ctl` (`EMBODY_PG_BIN`, Debian's layout, or PATH)."""
    if os.environ.get("EMBODY_PG_BIN"):
        return Path(os.environ["EMBODY_PG_BIN"])
    for v in _VERSIONS:
        for d in _BIN_DIRS:
            p = Path(d.format(v=v))
            if (p / "initdb").is_file():
                return p
    found = shutil.which("initdb")
    return Path(found).parent if found else None


class LocalPostgres(LocalService):
    """`with LocalPostgres() as url:` a fresh cluster and database until the block ends.

    `url` is SQLAlchemy's `postgresql+asyncpg://embody@127.0.0.1:PORT/prefect` (what
    `PREFECT_API_DATABASE_CONNECTION_URL` takes)."""

    def __init__(self, folder: str | Path | None = None, port: int | None = None,
                 user: str = "embody", database: str = "prefect",
                 max_connections: int = 200) -> None:
        self.bin = postgres_bin()
        self.port = port or free_port()
        self.user, self.database, self.max_connections = user, database, max_connections
        self._own_folder = folder is None
        self.folder = Path(folder) if folder else Path(tempfile.mkdtemp(prefix="embody-pg-"))
        self.data = self.folder / "data"
        self.log = self.folder / "postgres.log"
        self._runas: list[str] = []
        self.started = False

    @property
    def url(self) -> str:
        return f"postgresql+asyncpg://{self.user}@127.0.0.1:{self.port}/{self.database}"

    def _run(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run([*self._runas, *args], capture_output=True, text=True,
                              timeout=timeout, cwd=self.folder)

    def start(self) -> str:
        if self.bin is None:
            raise RuntimeError("PostgreSQL is not installed (initdb not found; Debian: "
                               "apt-get install postgresql)")
        self.folder.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:  # postgres will not run as root: hand it the folder
            pw = pwd.getpwnam("postgres")
            os.chown(self.folder, pw.pw_uid, pw.pw_gid)
            self._runas = ["runuser", "-u", "postgres", "--"]
        done = self._run(str(self.bin / "initdb"), "-D", str(self.data), "-A", "trust",
                         "-U", self.user, "-E", "UTF8", "--no-sync")
        if done.returncode != 0:
            raise RuntimeError(f"initdb failed: {done.stderr.strip()[-500:]}")
        options = (f"-p {self.port} -k {self.folder} -c listen_addresses=127.0.0.1 "
                   f"-c max_connections={self.max_connections} -c fsync=off")
        done = self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-o", options,
                         "-l", str(self.log), "-w", "-t", "60", "start")
        if done.returncode != 0:
            log = self.log.read_text(errors="replace")[-800:] if self.log.is_file() else ""
            raise RuntimeError(f"pg_ctl start failed: {done.stderr.strip()[-300:]} {log}")
        self.started = True
        self._createdb()
        return self.url

    def pid(self) -> int:
        """The postmaster's process id (its backends are its children), -1 when not running."""
        try:
            return int((self.data / "postmaster.pid").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return -1

    def _createdb(self) -> None:
        deadline = time.monotonic() + 30
        while True:
            done = self._run(str(self.bin / "createdb"), "-h", "127.0.0.1", "-p", str(self.port),
                             "-U", self.user, self.database)
            if done.returncode == 0:
                return
            if time.monotonic() > deadline:
                raise RuntimeError(f"createdb failed: {done.stderr.strip()[-300:]}")
            time.sleep(0.3)

    def stop(self) -> None:
        if self.started:
            self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w",
                      "stop", timeout=60)
            self.started = False
        if self._own_folder:
            shutil.rmtree(self.folder, ignore_errors=True)
