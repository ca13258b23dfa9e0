"""The run's ephemeral Prefect server, started by embody before the flow, from a migrated database.

Left to itself, Prefect starts its ephemeral server (a uvicorn child serving
`prefect.server.api.server:create_app`) inside the flow call, when the first client needs an API.
A cold `embody run` then waited ~11 s before its first task (2026-11-27, 2 cores): the driver
imported Prefect's whole server package only to reach the class that starts the child (~2.2 s),
the child booted (~3 s), and it migrated a new SQLite database, as every fresh store has one
(~4.8 s).

`prefect_api` starts the same child itself (Prefect's own command and environment), with the
database copied from a template of Prefect's migrated, empty schema (one per Prefect version,
in embody's cache folder, saved from the first run's database), and yields while the child
boots so the driver can warm the steps meanwhile. The flow then talks to it through
`PREFECT_API_URL`, as to any server, so the driver never imports Prefect's server. One server
serves every flow of the process and stops at exit (SIGTERM included, `flows.env.on_sigterm`);
its pidfile lets the next run stop it if this one is killed (`flows.env.stop_orphans`). A
user's own server (`PREFECT_API_URL` set) is used as is.
"""

from __future__ import annotations

import atexit
import os
import shutil
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from importlib.metadata import version
from importlib.util import find_spec
from pathlib import Path

from embody.cache import cache_dir
from embody.flows.env import register_server
from embody.flows.server import free_port

__all__ = ["EphemeralServer", "database_template", "prefect_api", "running_server",
           "save_template", "seed_database"]

_DB = "prefect.db"
#: Settings that move Prefect's database elsewhere: then there is no SQLite file to seed.
_DB_SETTINGS = ("PREFECT_API_DATABASE_CONNECTION_URL", "PREFECT_SERVER_DATABASE_CONNECTION_URL")
#: Whether the server migrates its database when it starts (Prefect's two names for it).
_MIGRATE_SETTINGS = ("PREFECT_SERVER_DATABASE_MIGRATE_ON_START",
                     "PREFECT_API_DATABASE_MIGRATE_ON_START")
#: The child's environment on top of ours: what Prefect's `SubprocessASGIServer` sets.
_CHILD_ENV = {"PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
              "PREFECT__SERVER_FINAL": "1"}


def database_template() -> Path:
    """Where the migrated, empty database of the installed Prefect version is kept."""
    return cache_dir() / "prefect" / f"prefect-{version('prefect')}.db"


def _sqlite() -> bool:
    """Prefect keeps its database in `PREFECT_HOME`'s SQLite file (no other database set)."""
    return not any(os.environ.get(name) for name in _DB_SETTINGS)


def seed_database(home: str | Path) -> bool:
    """Copy the template into a `PREFECT_HOME` that has no database yet; True if it did.

    The server then skips its migration check (`EphemeralServer._child_env`)."""
    home, template = Path(home), database_template()
    target = home / _DB
    if not _sqlite() or target.exists() or not template.is_file():
        return False
    home.mkdir(parents=True, exist_ok=True)
    tmp = home / f".{_DB}.{os.getpid()}.tmp"
    try:
        shutil.copyfile(template, tmp)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return True


def save_template(home: str | Path) -> bool:
    """Save `home`'s migrated database as the template, emptied of rows; True if it did.

    SQLite's backup API copies a consistent snapshot while the server has it open; every table
    but Alembic's version row is then emptied, so no run's records travel to another store."""
    source, template = Path(home) / _DB, database_template()
    if not _sqlite() or template.is_file() or not source.is_file():
        return False
    template.parent.mkdir(parents=True, exist_ok=True)
    tmp = template.with_name(f".{template.name}.{os.getpid()}.tmp")
    try:
        with sqlite3.connect(source) as src, sqlite3.connect(tmp) as dst:
            src.backup(dst)
        src.close()
        dst.close()
        db = sqlite3.connect(tmp, isolation_level=None)  # autocommit: VACUUM needs it
        try:
            names = {r[0] for r in db.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")}
            if "alembic_version" not in names:
                return False  # not migrated (yet): nothing worth keeping
            for table in sorted(names - {"alembic_version"}):
                db.execute(f'DELETE FROM "{table}"')
            db.execute("PRAGMA journal_mode = DELETE")  # one self-contained file, no -wal
            db.execute("VACUUM")
        finally:
            db.close()
        os.replace(tmp, template)
    except sqlite3.Error:
        return False  # a template is an optimisation: never fail a run over it
    finally:
        tmp.unlink(missing_ok=True)
    return True


class EphemeralServer:
    """Prefect's ephemeral API server as a child of this process, on a free loopback port."""

    def __init__(self, home: str | Path, startup_timeout_s: float | None = None) -> None:
        self.home = Path(home)
        self.startup_timeout_s = startup_timeout_s or float(
            os.environ.get("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", 90))
        self.port = 0
        self.proc: subprocess.Popen | None = None
        self.seeded = False
        self._pidfile: Path | None = None
        self._booting: threading.Thread | None = None
        self._error: str | None = None

    @property
    def log_path(self) -> Path:
        """The server's stdout and stderr (`$PREFECT_HOME/server.log`)."""
        return self.home / "server.log"

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    def start(self) -> None:
        """Spawn the child and watch it boot in a thread (returns at once; `wait` joins)."""
        self.seeded = seed_database(self.home)
        self._spawn()
        self._booting = threading.Thread(target=self._boot, name="prefect-server-boot",
                                         daemon=True)
        self._booting.start()

    def _spawn(self) -> None:
        spec = find_spec("prefect")  # where it is, without importing it here
        assert spec is not None and spec.origin is not None, "prefect is not installed"
        app_dir = str(Path(spec.origin).parent.parent)
        self.port = free_port()
        try:  # the server's own log (its errors repeat per retried request): not the run's stderr
            log = open(self.log_path, "wb")
        except OSError:
            log = subprocess.DEVNULL  # type: ignore[assignment]
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "--app-dir", app_dir, "--factory",
                 "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port",
                 str(self.port), "--log-level", "error", "--lifespan", "on"],
                env=self._child_env(), stdout=log, stderr=log)
        finally:
            if log is not subprocess.DEVNULL:
                log.close()
        self._pidfile = register_server(self.proc.pid, self.home)

    def _child_env(self) -> dict[str, str]:
        """Our environment, the home and what Prefect's own ephemeral server sets. A database
        copied from this Prefect's migrated template is already at Alembic's head, so the
        server skips its migration check (Alembic reading Prefect's ~200 revision files at
        every boot) unless the user set `..._MIGRATE_ON_START` themselves."""
        env = {**os.environ, "PREFECT_HOME": str(self.home), **_CHILD_ENV}
        if self.seeded and not any(n in os.environ for n in _MIGRATE_SETTINGS):
            env[_MIGRATE_SETTINGS[0]] = "false"
        return env

    def wait(self) -> str:
        """Block until the server is up; returns the API URL (RuntimeError if it never is)."""
        if self._booting is not None:
            self._booting.join()
        if self._error is not None:
            raise RuntimeError(self._error)
        return self.api_url

    def _boot(self) -> None:
        """Poll the health check (respawning if uvicorn lost its port), then save the database
        template and send the first reads, whose one-off server-side costs (database session,
        ORM) would otherwise delay the flow's first request."""
        deadline = time.monotonic() + self.startup_timeout_s
        retries = 2
        while time.monotonic() < deadline:
            assert self.proc is not None
            code = self.proc.poll()
            if code is not None:
                if code == 3 and retries:  # uvicorn: the port was taken meanwhile
                    retries -= 1
                    self._spawn()
                    continue
                self._error = (f"the Prefect server (PREFECT_HOME={self.home}) exited with code "
                               f"{code} while starting (its log: {self.log_path})")
                return
            if self._get("health"):
                if not self.seeded:
                    save_template(self.home)
                for path in ("flow_runs/filter", "task_runs/filter"):
                    self._get(path, body=b"{}")
                return
            time.sleep(0.05)
        self.stop()
        self._error = (f"the Prefect server did not start within {self.startup_timeout_s:.0f} s "
                       "(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS)")

    def _get(self, path: str, body: bytes | None = None) -> bool:
        """True when `path` answers 200 (a POST with a JSON `body`)."""
        request = urllib.request.Request(f"{self.api_url}/{path}", data=body,
                                         headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=5) as reply:
                return reply.status == 200
        except (urllib.error.URLError, OSError):
            return False

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._pidfile is not None:
            self._pidfile.unlink(missing_ok=True)


_SERVER: EphemeralServer | None = None
_LOCK = threading.Lock()


def running_server() -> EphemeralServer | None:
    """This process's ephemeral server, if `prefect_api` started one."""
    return _SERVER


def _configured_api() -> str | None:
    """The API the user configured (environment, or Prefect's settings once imported)."""
    if os.environ.get("PREFECT_API_URL"):
        return os.environ["PREFECT_API_URL"]
    home = os.environ.get("PREFECT_HOME")
    if "prefect.settings" in sys.modules or (home and (Path(home) / "profiles.toml").is_file()):
        from prefect.settings import get_current_settings
        return get_current_settings().api.url
    return None


@contextmanager
def _api_url(url: str) -> Iterator[None]:
    """`PREFECT_API_URL` for the block: in the environment (child processes, a Prefect not yet
    imported) and in Prefect's settings context when it is. Flow-run heartbeats are off: they
    let a server tell a crashed run, and this server ends with its run's process (their thread
    also held up each flow's end by up to a second)."""
    old = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = url
    try:
        if "prefect.settings" in sys.modules:
            from prefect import settings
            with settings.temporary_settings(updates={
                    settings.PREFECT_API_URL: url,
                    settings.PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
                yield
        else:
            yield
    finally:
        if old is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = old


@contextmanager
def prefect_api(warm: Callable[[], None] | None = None) -> Iterator[str | None]:
    """A Prefect API for the block: the user's, or this process's ephemeral server, started now
    (needs `PREFECT_HOME`: `flows.env.configure`). `warm()` runs while the server boots."""
    global _SERVER
    configured = _configured_api()
    if configured:
        if warm is not None:
            warm()
        yield configured
        return
    with _LOCK:
        server = _SERVER
        if server is None or not server.alive():
            home = os.environ.get("PREFECT_HOME")
            if not home:
                raise RuntimeError("PREFECT_HOME is not set: call embody.flows.env.configure "
                                   "first")
            server = EphemeralServer(Path(home).expanduser())
            # known (and stopped at exit) before its child exists: a SIGTERM that lands
            # between the spawn and the assignment left the server running (CI, 2026-11-27)
            if _SERVER is None:
                atexit.register(lambda: _SERVER is not None and _SERVER.stop())
            _SERVER = server
            server.start()
        if warm is not None:
            warm()
        url = server.wait()
    with _api_url(url):
        yield url
