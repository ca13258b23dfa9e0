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

An object store has no lock that dies with its holder, so there a claim is a lease
(`claimed_object`): `runs/.locks/<run>.claim.json` lists its live holders, each renewing its
own entry every few seconds; every change is a conditional write on the version read (S3
`If-Match`, `If-None-Match: *` for the first claim), so two claimants never both win. A holder
is live while it renews (or, on this host, while its PID runs): a killed run frees the name
within `LEASE_S` seconds, at once on its own host. `claim_run` picks the kind by the store.
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

__all__ = ["LEASE_S", "claim_run", "claimed", "claimed_object"]

#: A holder on another host that has not renewed its claim for this long is gone.
LEASE_S = 30.0


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


def claim_run(store: Any, run: str, identity: dict[str, Any]) -> Any:
    """The claim of run name `run` in `store` (an ArtifactStore), local or object store."""
    if store.objects is None:
        return claimed(store.runs_dir / run, identity)
    return claimed_object(store.objects, run, identity)


def _holder_live(holder: dict[str, Any], now: float) -> bool:
    from embody.store.artifacts import pid_alive

    if holder.get("host") == socket.gethostname():
        return pid_alive(int(holder.get("pid") or -1))
    return now - float(holder.get("renewed") or 0) < LEASE_S


def _update(objects: Any, key: str, change: Any) -> dict[str, Any]:
    """Apply `change(doc or None) -> doc` to the claim object by compare-and-swap."""
    from embody.store.objects import Conflict

    for attempt in range(1000):
        got = objects.get(key)
        try:
            doc = json.loads(got[0]) if got is not None else None
        except ValueError:
            doc = None
        new = change(doc)
        try:
            objects.put(key, json.dumps(new, sort_keys=True).encode("utf-8"),
                        create=got is None, etag=got[1] if got is not None else None)
            return new
        except Conflict:
            time.sleep(min(0.5, 0.005 * 2 ** min(attempt, 7)))
    raise TimeoutError(f"{objects.url}/{key}: 1000 conflicting claimants in a row")


@contextmanager
def claimed_object(objects: Any, run: str, identity: dict[str, Any]) -> Iterator[None]:
    """`claimed` on an object store: a lease renewed by a thread while the block runs."""
    import threading
    import uuid

    key = f"runs/{LOCKS}/{run}.claim.json"
    me = f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"

    def join(doc: dict[str, Any] | None) -> dict[str, Any]:
        now = time.time()
        holders = {h: v for h, v in ((doc or {}).get("holders") or {}).items()
                   if _holder_live(v, now)}
        if holders:
            live = {k: v for k, v in (doc or {}).items() if k != "holders"}
            what = _differs(live, identity)
            if what:
                raise ConfigError("run.name", f"run {run!r} is being computed now "
                                  f"(pid {live.get('pid', '?')}) over another " +
                                  " and ".join(what) + ": wait for it or pick another --name")
            base = live
        else:
            base = {**identity, "pid": os.getpid(), "host": socket.gethostname(), "time": now}
        holders[me] = {"pid": os.getpid(), "host": socket.gethostname(), "renewed": now}
        return {**base, "holders": holders}

    def renew(doc: dict[str, Any] | None) -> dict[str, Any]:
        doc = dict(doc or {})
        holders = dict(doc.get("holders") or {})
        holders[me] = {"pid": os.getpid(), "host": socket.gethostname(), "renewed": time.time()}
        return {**doc, "holders": holders}

    def leave(doc: dict[str, Any] | None) -> dict[str, Any]:
        doc = dict(doc or {})
        doc["holders"] = {h: v for h, v in (doc.get("holders") or {}).items() if h != me}
        return doc

    _update(objects, key, join)
    stop = threading.Event()

    def keep() -> None:
        while not stop.wait(LEASE_S / 3):
            try:
                _update(objects, key, renew)
            except Exception:  # a missed renewal only shortens the lease
                pass

    thread = threading.Thread(target=keep, name="embody-claim", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        try:
            _update(objects, key, leave)
        except Exception:  # the lease runs out by itself
            pass
