"""Whole-file writes for the exported library: a reader sees the previous file or the complete
new one, never a truncated one (a full disk mid-write leaves nothing behind), and a symlink
planted under the file's name is replaced, never written through."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def write_atomic(path: Path, data: bytes, accept: Callable[[Path], bool] | None = None) -> bool:
    """Write `data` to a new temp file beside `path`, fsync it and rename it onto `path`.

    `accept(temp)`, when given, sees the complete temp file first; if it returns False the temp
    is removed, `path` is left as it was, and False is returned. Any error (ENOSPC included)
    removes the temp and propagates. The rename replaces whatever entry `path` is, a symlink
    included, so nothing outside the folder is ever written.
    """
    path = Path(path)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    tmp = Path(name)
    try:
        try:
            _write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; exported files are ordinary files
        if accept is not None and not accept(tmp):
            tmp.unlink()
            return False
        os.replace(tmp, path)
        return True
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def sync_dir(folder: Path) -> None:
    """fsync a folder, so the renames into it survive a power cut (best effort)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
