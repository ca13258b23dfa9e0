"""Where a report's files are (a plain record, importable without the report's heavy deps)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["ReportPaths", "safe_name"]


@dataclass(frozen=True)
class ReportPaths:
    """Where everything of one report was written."""

    out_dir: Path
    index: Path
    summary: Path
    sequences: Path
    tables: dict[str, dict[str, Path]] = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)


def safe_name(sid: str) -> str:
    """A sequence id as a file name; ids with slashes or spaces get a short hash so that
    "a/b" and "a_b" stay distinct."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in sid)
    if safe == sid:
        return sid
    return f"{safe}-{hashlib.sha1(sid.encode('utf-8')).hexdigest()[:8]}"
