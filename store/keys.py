"""Content keys: the cache identity of every artifact.

A key hashes exactly what determines an artifact's content: the step name, an explicit code
version (bumped by hand when a step's output changes, because source hashing misses helpers),
the canonical JSON of the config sections the step reads, and the keys of its inputs. Source
artifacts hash the bytes of their files instead, so renaming a file keeps its key.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

__all__ = ["content_key", "files_key", "arrays_checksum"]


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def content_key(step: str, version: str, config: Mapping[str, str],
                inputs: Mapping[str, str]) -> str:
    """Key of a computed artifact.

    `config` maps section name → `Config.section_json(name)`; `inputs` maps input name → key.
    Both are sorted, so the key does not depend on argument order.
    """
    doc = {"step": step, "version": str(version),
           "config": {k: config[k] for k in sorted(config)},
           "inputs": {k: inputs[k] for k in sorted(inputs)}}
    return _sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")))


def _update_file(h: "hashlib._Hash", path: Path) -> None:
    """Length-prefixed bytes, streamed: a source file may be large."""
    h.update(path.stat().st_size.to_bytes(8, "little"))
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)


def _folder_files(folder: Path) -> list[Path]:
    """A sequence folder's frame files: every visible regular file, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))


def files_key(paths: Iterable[str | Path], extra: str = "") -> str:
    """Key of source files: their bytes in the given order (names do not matter), plus `extra`.

    A folder (a per-frame sequence such as SOKE's) contributes its frame files sorted by name,
    each with its name, since the names fix the frame order.
    """
    h = hashlib.sha256()
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files = _folder_files(p)
            h.update(b"dir" + len(files).to_bytes(8, "little"))
            for f in files:
                h.update(f.name.encode("utf-8", "surrogateescape") + b"\0")
                _update_file(h, f)
        else:
            _update_file(h, p)
    h.update(extra.encode("utf-8"))
    return h.hexdigest()


def arrays_checksum(arrays: Mapping[str, np.ndarray]) -> str:
    """Checksum of array contents (name, dtype, shape, C-order bytes): what `verify` re-hashes."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode("utf-8"))
        h.update(a.tobytes())
    return h.hexdigest()
