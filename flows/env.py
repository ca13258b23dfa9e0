"""Offline-by-default Prefect settings; call `configure` before the first `import prefect`.

Prefect reads its settings from the environment when it is imported, so these are plain
`os.environ` defaults: anything the user already set (a real `PREFECT_API_URL`, their own
`PREFECT_HOME`) wins.

The ephemeral Prefect server is a child process that Prefect stops at interpreter exit. SIGTERM
is turned into the same exit path as Ctrl-C (`on_sigterm`): VLM requests in flight are ended at
once, and a run that has not exited `grace_s` later, or gets a second SIGTERM, stops its Prefect
server and exits (143) without waiting for its worker threads. Each run leaves a pidfile
(`$PREFECT_HOME/embody-servers/<pid>.json`) naming its server and itself, so after a SIGKILL
the next run over the same store finds the orphaned server and stops it (`stop_orphans`).
"""

from __future__ import annotations

import atexit
import json
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

__all__ = ["configure", "on_sigterm", "register_server", "sigterm_inside_flow", "stop_orphans"]

_DEFAULTS = {
    "DO_NOT_TRACK": "1",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_LOGGING_INTERNAL_LEVEL": "ERROR",
    # The ephemeral server registers Prefect's block types into its database at every start
    # (~3 s of each run's start-up here); embody uses no blocks (results live in the store).
    "PREFECT_SERVER_REGISTER_BLOCKS_ON_START": "false",
}
_PIDS = "embody-servers"
#: Pidfiles this process wrote (removed at exit, or by `_hard_exit`).
_PIDFILES: list[Path] = []


def configure(store_root: str | Path) -> None:
    """Ephemeral local Prefect, no telemetry, quiet logs, `PREFECT_HOME` inside the store;
    Prefect servers orphaned by killed runs of this store are stopped first."""
    for name, value in _DEFAULTS.items():
        os.environ.setdefault(name, value)
    home = os.environ.setdefault("PREFECT_HOME",
                                 str(Path(store_root).expanduser().resolve() / "prefect"))
    Path(home).expanduser().mkdir(parents=True, exist_ok=True)  # SQLite will not create it
    for pid in stop_orphans(home):
        print(f"stopped an orphaned Prefect server (pid {pid}) left by a killed run",
              file=sys.stderr)


#: Seconds a SIGTERMed run may take to unwind (finishing the step calls in flight) before it
#: exits without them.
SIGTERM_GRACE_S = 10.0


def _abort_requests() -> None:
    """End the VLM requests in flight (a request may otherwise wait `critic.vlm.timeout_s`)."""
    vlm = sys.modules.get("embody.critic.vlm")
    if vlm is not None:
        vlm.abort_requests()


def _hard_exit(code: int = 143) -> None:
    """Stop this process's Prefect server, remove its pidfile and exit now; worker threads
    are not waited for (worker processes die with their parent)."""
    ephemeral = sys.modules.get("embody.flows.ephemeral")
    server = ephemeral.running_server() if ephemeral is not None else None
    try:
        if server is not None:
            server.stop()
        for path in _PIDFILES:
            path.unlink(missing_ok=True)
        print("stopped (SIGTERM): work in flight abandoned", file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


_SIGTERM: dict[str, Any] = {"installed": False, "received": 0, "relay": False,
                            "grace_s": SIGTERM_GRACE_S}


def _on_signal() -> None:
    """What every SIGTERM does first: end VLM requests, then arm the grace timer (first
    signal) or exit now (second)."""
    _SIGTERM["received"] += 1
    _abort_requests()
    if _SIGTERM["received"] > 1:
        _hard_exit()
    timer = threading.Timer(_SIGTERM["grace_s"], _hard_exit)
    timer.daemon = True
    timer.start()


def _handler(signum: int, frame: object) -> None:
    if _SIGTERM["relay"]:  # Prefect's flow engine re-sends the SIGTERM it took over
        _SIGTERM["relay"] = False
    else:
        _on_signal()
    raise KeyboardInterrupt(f"signal {signum}")


def on_sigterm(grace_s: float = SIGTERM_GRACE_S) -> None:
    """SIGTERM raises KeyboardInterrupt in the main thread: the same cleanup as Ctrl-C (the
    ephemeral server is stopped at exit). VLM requests in flight end at once; if the process
    is still there `grace_s` later (a step call that cannot be interrupted), or on a second
    SIGTERM, it exits through `_hard_exit`. Only the main thread may install handlers."""
    _SIGTERM["grace_s"] = grace_s
    try:
        signal.signal(signal.SIGTERM, _handler)
    except ValueError:  # not the main thread
        return
    _SIGTERM["installed"] = True


@contextmanager
def sigterm_inside_flow() -> Iterator[None]:
    """Prefect's flow engine installs its own SIGTERM handler for the flow's duration (it
    raises `TerminationSignal`, then waits for the task runner's calls in flight). Where
    `on_sigterm` is in force, the flow's handler is chained after `_on_signal`, so a SIGTERM
    during the flow also ends VLM requests and arms the grace timer."""
    if not _SIGTERM["installed"] or threading.current_thread() is not threading.main_thread():
        yield
        return
    prev = signal.getsignal(signal.SIGTERM)
    if prev is _handler or not callable(prev):
        yield
        return

    def chained(signum: int, frame: Any) -> None:
        _on_signal()
        _SIGTERM["relay"] = True
        prev(signum, frame)

    signal.signal(signal.SIGTERM, chained)
    try:
        yield
    finally:
        if signal.getsignal(signal.SIGTERM) is chained:
            signal.signal(signal.SIGTERM, prev)


def register_server(pid: int | None = None, home: str | Path | None = None) -> Path | None:
    """Write the pidfile of this process's ephemeral Prefect server `pid` (default: one Prefect
    started itself; None when there is none, e.g. with a real `PREFECT_API_URL`) under `home`
    (default `$PREFECT_HOME`); removed again at exit."""
    home = home or os.environ.get("PREFECT_HOME")
    if pid is None:
        pid = _prefect_started_server()
    if not home or pid is None:
        return None
    folder = Path(home).expanduser() / _PIDS
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{pid}.json"
    path.write_text(json.dumps({"server": pid, "owner": os.getpid(),
                                "home": str(Path(home).expanduser().resolve()),
                                "time": time.time()}))
    atexit.register(lambda: path.unlink(missing_ok=True))
    _PIDFILES.append(path)
    return path


def _prefect_started_server() -> int | None:
    """The pid of an ephemeral server Prefect started itself in this process (a flow called
    without `flows.ephemeral.prefect_api`), if its server module is loaded at all."""
    module = sys.modules.get("prefect.server.api.server")
    if module is None:
        return None
    procs = [s.server_process for s in list(module.SubprocessASGIServer._instances.values())
             if getattr(s, "server_process", None) is not None]
    procs = [p for p in procs if p.poll() is None]
    return procs[0].pid if procs else None


def _is_prefect_server(pid: int, home: Path) -> bool:
    """The process is a Prefect uvicorn server of this PREFECT_HOME (guards against pid reuse)."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    if b"uvicorn" not in cmd or b"prefect" not in cmd:
        return False
    try:
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return True  # cmdline matched; environ unreadable
    return f"PREFECT_HOME={home}".encode() in env or not any(
        e.startswith(b"PREFECT_HOME=") for e in env)


def stop_orphans(home: str | Path, wait_s: float = 5.0) -> list[int]:
    """Stop the Prefect servers whose owning run is gone; returns their pids."""
    from embody.store.artifacts import pid_alive  # zarr & numpy: only when there are pidfiles

    folder = Path(home).expanduser() / _PIDS
    if not folder.is_dir():
        return []
    stopped = []
    for path in sorted(folder.glob("*.json")):
        try:
            info = json.loads(path.read_text())
            server, owner = int(info["server"]), int(info["owner"])
        except (OSError, ValueError, KeyError, TypeError):
            path.unlink(missing_ok=True)
            continue
        if pid_alive(owner):
            continue
        if pid_alive(server) and _is_prefect_server(server, Path(info.get("home", home))):
            os.kill(server, signal.SIGTERM)
            deadline = time.monotonic() + wait_s
            while pid_alive(server) and time.monotonic() < deadline:
                time.sleep(0.05)
            if pid_alive(server):
                os.kill(server, signal.SIGKILL)
            stopped.append(server)
        path.unlink(missing_ok=True)
    return stopped
