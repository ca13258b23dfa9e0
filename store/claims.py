"""Run claims: what a run name is being computed over right now.

A run's manifest records its dataset only once the run has started its flow, seconds after the
command began; before that a second `embody run` with the same `--name` and another dataset saw
no manifest, was accepted, and the two runs' manifests merged into one that named only the first
dataset (so `store gc` would delete the second run's artifacts). So `embody run` claims the name
before it writes anything: under the run's manifest lock (`store.writers.locked`) it records its
identity (dataset, split, robot) in `runs/.locks/<run>.claim.json` and holds a shared `flock` on
`runs/.locks/<run>.active` until it exits. A later claim that cannot take that lock exclusively
knows a run of the name is live and compares identities: another identity is refused, the same
one shares the name as before (a dataset split across processes with `run.offset`/`run.limit`).
The kernel drops the lock when its holder exits or dies, so a claim never goes stale.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from embody.errors import ConfigError
from embody.store.writers import LOCKS, locked

__all__ = ["claimed"]


def _paths(run_dir: Path) -> tuple[Path, Path]:
    folder = run_dir.parent / LOCKS
    return folder / f"{run_dir.name}.active", folder / f"{run_dir.name}.claim.json"


def _read(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _differs(live: dict[str, Any], identity: dict[str, Any]) -> list[str]:
    return [f"{k} {live.get(k)!r} (now {v!r})" for k, v in identity.items()
            if k in live and live[k] != v]


@contextmanager
def claimed(run_dir: Path, identity: dict[str, Any]) -> Iterator[None]:
    """Claim the run name of `run_dir` for `identity` (JSON values) for the block; ConfigError
    (exit 2) when a live run of the name has another identity. Nothing else is written."""
    active, record = _paths(run_dir)
    with locked(run_dir):
        fd = os.open(active, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                live = None
            except BlockingIOError:
                live = _read(record) or {}
            if live is not None:
                what = _differs(live, identity)
                if what:
                    raise ConfigError("run.name", f"run {run_dir.name!r} is being computed now "
                                      f"(pid {live.get('pid', '?')}) over another " +
                                      " and ".join(what) + ": wait for it or pick another --name")
            else:
                tmp = record.with_name(f".{record.name}.{os.getpid()}.tmp")
                try:
                    tmp.write_text(json.dumps({**identity, "pid": os.getpid(),
                                               "host": socket.gethostname(),
                                               "time": time.time()}), encoding="utf-8")
                    os.replace(tmp, record)
                finally:
                    tmp.unlink(missing_ok=True)
            fcntl.flock(fd, fcntl.LOCK_SH)  # the live mark, shared with same-identity runs
        except BaseException:
            os.close(fd)
            raise
    try:
        yield
    finally:
        os.close(fd)  # releases the shared lock
