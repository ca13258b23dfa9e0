"""Is a report current? The digest of what a store-built report was made from.

Kept apart from the writers (no matplotlib, torch or pandas here), so a fully cached
`embody run` can tell in milliseconds that its report needs no rebuilding.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from embody.report.paths import ReportPaths

#: Beside a report: the digest of what it was built from (see `source_digest`).
SOURCE_STAMP = ".embody-report-source"


def source_digest(manifest_path: Path | None = None, *, text: str | None = None) -> str:
    """What a store-built report depends on: the run manifest (minus its timestamps and writer
    bookkeeping) and the report code. Equal digests mean rebuilding would write the same report.
    The manifest is read from `manifest_path`, or given as `text` (an object store's)."""
    data = json.loads(text if text is not None else Path(manifest_path).read_text())
    for volatile in ("created", "finished", "done_at", "writers"):
        data.pop(volatile, None)
    h = hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode())
    here = Path(__file__).resolve().parent
    for code in sorted([*here.glob("*.py"), here.parent / "verdicts.py"]):
        h.update(code.read_bytes())
    return h.hexdigest()


def current_report(out_dir: Path, digest: str) -> ReportPaths | None:
    """The report already in `out_dir` when it was built from `digest`, else None."""
    stamp, index = out_dir / SOURCE_STAMP, out_dir / "index.html"
    try:
        if stamp.read_text().strip() != digest or not index.is_file():
            return None
    except OSError:
        return None
    tables = {p.stem: {e: p.with_suffix(f".{e}") for e in ("csv", "md", "tex")}
              for p in sorted(out_dir.glob("*.md"))}
    return ReportPaths(out_dir=out_dir, index=index, summary=out_dir / "summary.json",
                       sequences=out_dir / "sequences.csv", tables=tables,
                       figures=sorted((out_dir / "figures").rglob("*.png")))


def stamp_report(out_dir: Path, digest: str) -> None:
    (out_dir / SOURCE_STAMP).write_text(digest + "\n")
