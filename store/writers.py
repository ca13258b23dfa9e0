"""Several processes writing one run's manifest: read-merge-write under a kernel lock.

Two `embody run` processes with the same run name and store (e.g. a dataset split across
machines with `run.offset`/`run.limit`) each hold only their own sequences. Every save takes an
exclusive `flock` on `runs/.locks/<run>.lock`, reads the manifest on disk, merges its own
entries into it and replaces it atomically, so no writer ever drops another's sequences.

The kernel releases a `flock` when its holder exits or dies (even on `kill -9`), so a lock can
never go stale and block a rerun; the lock file is an empty, harmless placeholder. The lock is
held only for one read-merge-write (milliseconds to about a second for a 20k-sequence run).

Merge rules, per sequence id:
- ids this writer runs take its entry, except that a pending entry of ours yields to a finished
  (`ok`/`failed`) entry another writer finished after we started (a concurrent run got there
  first; the content keys are the same);
- ids only others run are kept as they are: a run name accumulates its sequences;
- `shared` keys are merged; `finished` is stamped only when no other writer is still live
  (`writers` lists the live ones: same host and PID alive, or seen within a day elsewhere), so a
  garbage collector treats the run as in progress while any of its writers is.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

__all__ = ["LOCKS", "ObjectRunWriter", "RunWriter", "locked", "merge", "writer_alive"]

#: Lock files live beside the run folders (`runs/.locks/<run>.lock`), never inside one.
LOCKS = ".locks"
#: A writer on another host that has not saved for this long is taken as gone.
REMOTE_TTL_S = 24 * 3600.0
_DONE = ("ok", "failed")


def _proc_start(pid: int) -> float | None:
    """The process' start time (tells a live writer from a reused PID), when psutil is there."""
    try:
        import psutil
        return float(psutil.Process(pid).create_time())
    except Exception:  # psutil missing, or no such process
        return None


def writer_alive(writer: dict[str, Any], now: float | None = None) -> bool:
    """Whether a recorded writer may still be running (when unsure, yes for a day)."""
    now = time.time() if now is None else now
    if writer.get("host") != socket.gethostname():
        return now - float(writer.get("saved") or writer.get("started") or 0) < REMOTE_TTL_S
    pid = int(writer.get("pid") or -1)
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    recorded, actual = writer.get("proc_start"), _proc_start(pid)
    return recorded is None or actual is None or abs(actual - float(recorded)) < 1.0


@contextmanager
def locked(run_dir: Path, timeout_s: float = 300.0) -> Iterator[None]:
    """Hold the run's manifest lock; TimeoutError if a live process holds it longer."""
    lock = run_dir.parent / LOCKS / f"{run_dir.name}.lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        deadline, wait = time.monotonic() + timeout_s, 0.002
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{lock}: held by a live process for over "
                                       f"{timeout_s:.0f} s") from None
                time.sleep(wait)
                wait = min(2 * wait, 0.1)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def _done(entry: dict[str, Any] | None) -> bool:
    return bool(entry) and entry.get("status") in _DONE


def merge(disk: dict[str, Any] | None, mine: dict[str, Any], writer: dict[str, Any],
          finished: float | None, now: float | None = None) -> dict[str, Any]:
    """The manifest to write: `disk` (what is there, or None) with this writer's `mine` merged in.

    `mine["done_at"]` (sequence id → when it finished) is stamped here for newly finished ones.
    """
    now = time.time() if now is None else now
    if not isinstance(disk, dict) or not isinstance(disk.get("sequences"), dict):
        disk = {}
    theirs_seq: dict[str, Any] = disk.get("sequences", {})
    theirs_done: dict[str, float] = dict(disk.get("done_at") or {})
    mine_done: dict[str, float] = mine.setdefault("done_at", {})
    sequences = dict(theirs_seq)
    done_at = theirs_done
    for sid, entry in mine["sequences"].items():
        if _done(entry):
            mine_done.setdefault(sid, now)
        else:
            mine_done.pop(sid, None)
        other = theirs_seq.get(sid)
        if (not _done(entry) and _done(other) and other is not entry
                and theirs_done.get(sid, 0.0) >= writer["started"]):
            continue  # a concurrent writer finished it after we started
        sequences[sid] = entry
        if sid in mine_done:
            done_at[sid] = mine_done[sid]
        else:
            done_at.pop(sid, None)
    others = {wid: w for wid, w in (disk.get("writers") or {}).items()
              if wid != writer["id"] and writer_alive(w, now)}
    writers = dict(others)
    if finished is None:
        writers[writer["id"]] = dict(writer, saved=now)
    out = {k: v for k, v in mine.items() if k not in ("sequences", "done_at")}
    out.update(sequences=sequences, done_at=done_at, writers=writers,
               shared={**(disk.get("shared") or {}), **(mine.get("shared") or {})},
               created=min(float(disk.get("created") or now), float(mine.get("created") or now)),
               finished=finished if not others else None)
    return out


def _signature(path: Path) -> tuple[int, int, int] | None:
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


class RunWriter:
    """One process' writes to one manifest; `Manifest.save` goes through `save`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._identity: dict[str, Any] | None = None
        self._last: tuple[tuple[int, int, int] | None, dict[str, Any] | None] = (None, None)

    @property
    def identity(self) -> dict[str, Any]:
        if self._identity is None:
            pid = os.getpid()
            self._identity = {"id": f"{socket.gethostname()}-{pid}-{uuid.uuid4().hex[:8]}",
                              "host": socket.gethostname(), "pid": pid,
                              "proc_start": _proc_start(pid), "started": time.time()}
        return self._identity

    def save(self, data: dict[str, Any], write: Any) -> dict[str, Any]:
        """Merge `data` into the manifest on disk under the lock, write it with `write(path,
        doc)`; returns what was written."""
        finished = data.get("finished")
        with locked(self.path.parent):
            sig, cached = self._last
            if cached is not None and sig is not None and sig == _signature(self.path):
                disk = cached  # nobody wrote since we did: skip re-reading a big manifest
            else:
                try:
                    disk = json.loads(self.path.read_text())
                except (OSError, ValueError):
                    disk = None  # absent or unreadable: nothing of others' to keep
            doc = merge(disk, data, self.identity, finished)
            write(self.path, doc)
            self._last = (_signature(self.path), doc)
        return doc


class ObjectRunWriter:
    """`RunWriter` on an object store, which has no lock: the same read-merge-write, made safe
    by writing the merged manifest only if it is still the version that was read (S3
    `If-Match: <ETag>`, `If-None-Match: *` for the first). A writer that loses re-reads and
    merges again, so no writer ever drops another's sequences."""

    def __init__(self, objects: Any, key: str) -> None:
        self.objects, self.key = objects, key
        self.path = f"{objects.url}/{key}"
        self._writer = RunWriter(Path(key))  # only for its identity
        self._last: tuple[str | None, dict[str, Any] | None] = (None, None)

    @property
    def identity(self) -> dict[str, Any]:
        return self._writer.identity

    def save(self, data: dict[str, Any], write: Any = None) -> dict[str, Any]:
        """Merge `data` into the stored manifest and write it (compare-and-swap, retried)."""
        from embody.store.objects import Conflict

        finished = data.get("finished")
        wait = 0.005
        for _ in range(1000):
            etag, cached = self._last
            if etag is None or cached is None:
                got = self.objects.get(self.key)
                try:
                    disk, etag = (json.loads(got[0]), got[1]) if got is not None else (None, None)
                except ValueError:
                    disk = None  # unreadable: nothing of others' to keep
                exists = got is not None
            else:
                disk, exists = cached, True  # our own last write: if it changed, the put fails
            doc = merge(disk, data, self.identity, finished)
            body = json.dumps(doc, indent=1, sort_keys=True, default=str).encode("utf-8")
            try:
                new = self.objects.put(self.key, body, create=not exists,
                                       etag=etag if exists else None)
            except Conflict:
                self._last = (None, None)
                time.sleep(wait * (0.5 + uuid.uuid4().int % 1000 / 1000))
                wait = min(2 * wait, 0.5)
                continue
            self._last = (new, doc) if new else (None, None)
            return doc
        raise TimeoutError(f"{self.path}: 1000 conflicting writers in a row")
