"""The arrays a worker just published, kept for the same run's next steps to read.

A sequence's steps run one after another in the same worker, and each read of an input went
back to the store: a zarr open, the chunk reads and a digest check, 5-20 ms each, ~13 per
sequence in the default run (2026-11-27). This keeps the arrays of what this process published
in this run session (the same bytes the store's digests describe), bounded in bytes, and hands
out copies, so no step sees another's changes. Only the run that published an artifact reads it
from here: a file damaged on disk afterwards is still caught by the next run's checks.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

__all__ = ["forget", "recall", "remember"]

#: Bytes kept at most (oldest out first); the default run's 24 sequences publish ~31 MB.
CAPACITY = 256 * 2**20

_MEMO: OrderedDict[tuple[str, str, str], dict[str, np.ndarray]] = OrderedDict()
_SIZE = {"bytes": 0}
_LOCK = threading.Lock()


def _nbytes(arrays: dict[str, np.ndarray]) -> int:
    return sum(a.nbytes for a in arrays.values())


def remember(session: str, step: str, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Keep a copy of the arrays `step` published under `key` in this run `session`."""
    kept = {name: np.array(a, copy=True, order="C") for name, a in arrays.items()}
    size = _nbytes(kept)
    if size > CAPACITY:
        return
    with _LOCK:
        old = _MEMO.pop((session, step, key), None)
        if old is not None:
            _SIZE["bytes"] -= _nbytes(old)
        _MEMO[(session, step, key)] = kept
        _SIZE["bytes"] += size
        while _SIZE["bytes"] > CAPACITY:
            _, dropped = _MEMO.popitem(last=False)
            _SIZE["bytes"] -= _nbytes(dropped)


def recall(session: str, step: str, key: str) -> dict[str, np.ndarray] | None:
    """Copies of the arrays `remember` kept, or None."""
    with _LOCK:
        arrays = _MEMO.get((session, step, key))
        if arrays is None:
            return None
        _MEMO.move_to_end((session, step, key))
    return {name: a.copy() for name, a in arrays.items()}


def forget(session: str, step: str, key: str) -> None:
    with _LOCK:
        old = _MEMO.pop((session, step, key), None)
        if old is not None:
            _SIZE["bytes"] -= _nbytes(old)
