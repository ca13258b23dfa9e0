"""Offline-by-default Prefect settings; call `configure` before the first `import prefect`.

Prefect reads its settings from the environment when it is imported, so these are plain
`os.environ` defaults: anything the user already set (a real `PREFECT_API_URL`, their own
`PREFECT_HOME`) wins.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["configure"]

_DEFAULTS = {
    "DO_NOT_TRACK": "1",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_LOGGING_INTERNAL_LEVEL": "ERROR",
}


def configure(store_root: str | Path) -> None:
    """Ephemeral local Prefect, no telemetry, quiet logs, `PREFECT_HOME` inside the store."""
    for name, value in _DEFAULTS.items():
        os.environ.setdefault(name, value)
    home = os.environ.setdefault("PREFECT_HOME",
                                 str(Path(store_root).expanduser().resolve() / "prefect"))
    Path(home).expanduser().mkdir(parents=True, exist_ok=True)  # SQLite will not create it
