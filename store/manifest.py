"""Run manifests: which artifact each sequence's steps produced in one named run.

`runs/<run>/manifest.json` maps sequence id → {status, error, steps: {step: key}, metrics}. It is
rewritten atomically (temp + `os.replace`; on an object store one PUT, conditional on the
version it merged into: `store.writers.ObjectRunWriter`) as sequences finish, so a killed run
still leaves a valid manifest, and `gc` can tell which artifacts any run still references.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path
from typing import Any, Iterable

from embody.errors import ConfigError, InputError
from embody.store.artifacts import ArtifactStore
from embody.store.writers import ObjectRunWriter, RunWriter

__all__ = ["Manifest", "check_run_name", "load_manifests", "write_json_atomic"]

_RUN_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def check_run_name(name: str, key: str = "run.name") -> str:
    """A run name that stays one folder under `runs/` and `reports/`, else ConfigError.

    Names become directory names: `.`/`..` (or any all-dot name), separators and anything that
    resolves elsewhere would write the manifest outside `runs/` or the report into `./`.
    """
    if not isinstance(name, str) or not _RUN_NAME.match(name) or set(name) == {"."}:
        raise ConfigError(key, f"invalid run name {name!r}: use letters, digits, '_', '-' and "
                          "'.', not only dots")
    base = Path("/runs")
    if (base / name).resolve().parent != base:
        raise ConfigError(key, f"invalid run name {name!r}: it resolves outside runs/")
    return name


def write_json_atomic(path: Path, data: Any) -> None:
    """Temp + `os.replace`; the temp is removed when the write fails (a full disk leaves none).
    Streamed (`json.dump`), not one string: a 1,000-sequence manifest's text cost the driver a
    23 MB peak per save (460 MB at 20k sequences), the stream a few hundred KB, at equal speed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1, sort_keys=True, default=str)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


class Manifest:
    """The manifest of one run, as one driver process sees it (`store.writers` merges drivers)."""

    def __init__(self, store: ArtifactStore, run: str) -> None:
        self.store = store
        self.run = check_run_name(run)
        self.path = store.manifest_path(run)
        # concurrent writers of one run merge, never overwrite
        self.writer: RunWriter | ObjectRunWriter = (
            RunWriter(self.path) if store.objects is None
            else ObjectRunWriter(store.objects, f"runs/{run}/manifest.json"))
        self.data: dict[str, Any] = {"run": run, "created": time.time(), "shared": {},
                                     "sequences": {}}

    @classmethod
    def load(cls, store: ArtifactStore, run: str) -> "Manifest":
        """Read a run's manifest; an unreadable or malformed one is an InputError naming it
        (gc must stop rather than treat that run's artifacts as unreferenced)."""
        m = cls(store, run)
        try:
            text = store.read_manifest_text(run)
            if text is None:
                raise FileNotFoundError(f"no such manifest: {m.path}")
            m.data = json.loads(text)
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(m.path, None, f"corrupt run manifest: {type(exc).__name__}: "
                                           f"{' '.join(str(exc).split())}") from None
        seqs = m.data.get("sequences") if isinstance(m.data, dict) else None
        if not isinstance(seqs, dict) or not isinstance(m.data.get("shared", {}), dict) or not all(
                isinstance(s, dict) and isinstance(s.get("steps", {}), dict) for s in seqs.values()):
            raise InputError(m.path, "sequences", "corrupt run manifest: expected an object of "
                                                  "sequences, each with an object 'steps'")
        return m

    @property
    def sequences(self) -> dict[str, dict[str, Any]]:
        return self.data["sequences"]

    def start(self, ids: Iterable[str], **info: Any) -> None:
        """Begin (or restart) the run: every sequence pending, earlier results dropped."""
        self.data.update(info, created=time.time(), finished=None, shared={})
        self.data["sequences"] = {i: {"status": "pending", "error": None, "failed_step": None,
                                      "steps": {}, "metrics": {}} for i in ids}
        self.save()

    def update(self, record: dict[str, Any]) -> None:
        """Merge one sequence record produced by a step."""
        seq = self.sequences[record["id"]]
        seq["steps"].update(record.get("keys", {}))
        seq["metrics"].update(record.get("metrics", {}))
        for item in record.get("recovered", []):  # corrupt artifacts this run recomputed
            if item not in seq.setdefault("recovered", []):
                seq["recovered"].append(item)
        if record.get("status") == "failed":
            seq.update(status="failed", error=record.get("error"), failed_step=record.get("failed_step"))
            if record.get("traceback"):
                seq["traceback"] = record["traceback"]

    def set_shared(self, step: str, key: str | None) -> None:
        if key is not None:
            self.data["shared"][step] = key

    def finish_sequence(self, seq_id: str) -> None:
        seq = self.sequences[seq_id]
        if seq["status"] == "pending":
            seq["status"] = "ok"

    def save(self, finished: bool = False) -> None:
        if finished:
            self.data["finished"] = time.time()
        self.writer.save(self.data, write_json_atomic)

    def modified(self) -> float:
        """When the manifest was last written (epoch seconds)."""
        return self.store.manifest_mtime(self.run)

    @property
    def finished(self) -> bool:
        return self.data.get("finished") is not None

    def keys(self) -> set[tuple[str, str]]:
        """Every (step, key) this run references."""
        out = set(self.data.get("shared", {}).items())
        for seq in self.sequences.values():
            out.update(seq["steps"].items())
        return out


def load_manifests(store: ArtifactStore) -> list[Manifest]:
    """Every run's manifest (read only: a symlinked run still protects what it references)."""
    return [Manifest.load(store, run) for run in store.run_names()]
