"""embody's on-disk cache folder: derived data worth keeping across runs and stores.

What lives there is keyed by everything that determines it (a content hash or a package
version), so it is never stale, only unused: collision volumes, shape fits, the migrated
Prefect database template. `$EMBODY_CACHE` moves it (tests point it at a temporary folder).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_dir"]


def cache_dir() -> Path:
    """`$EMBODY_CACHE`, else `~/.cache/embody`."""
    return Path(os.environ.get("EMBODY_CACHE", Path.home() / ".cache" / "embody"))
