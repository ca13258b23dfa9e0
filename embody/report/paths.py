"""Where a report's files are (a plain record, importable without the report's heavy deps)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["ReportPaths"]


@dataclass(frozen=True)
class ReportPaths:
    """Where everything of one report was written."""

    out_dir: Path
    index: Path
    summary: Path
    sequences: Path
    tables: dict[str, dict[str, Path]] = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)
