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


def files_key(paths: Iterable[str | Path], extra: str = "") -> str:
    """Key of source files: their bytes in the given order (names do not matter), plus `extra`."""
    h = hashlib.sha256()
    for p in paths:
        data = Path(p).read_bytes()
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)
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
