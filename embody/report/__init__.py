"""Reports: the paper's tables, figures and an offline HTML page, read from a run's store.

A pure reader: it imports nothing of the robot, the body, the renderer, the critic or the stages
(the trajectory library export is `embody.export.library`).

`build_report(store_root, run)` is what `embody run` calls at the end; `write_report(data, dir)`
does the same from in-memory `RunData` (e.g. DataFrames built in a notebook). Names load on
first use (PEP 562), so checking whether a report is current never imports matplotlib or torch.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

__all__ = ["ReportPaths", "RunData", "Table", "build_report", "collect", "latest_run",
           "write_report"]

_LAZY = {
    "ReportPaths": "embody.report.paths", "default_out_dir": "embody.report.build",
    "write_report": "embody.report.build", "collect": "embody.report.reader",
    "latest_run": "embody.report.reader", "RunData": "embody.report.data",
    "Table": "embody.report.tables",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'embody.report' has no attribute {name!r}")


def build_report(store_root: str | Path, run_name: str, out_dir: str | Path | None = None,
                 *, reuse: bool = False) -> Any:
    """Write the report of `run_name` (default folder `./reports/<run_name>`).

    With `reuse`, a report already built from the same manifest content by the same report
    code is kept as it is (a fully cached rerun then takes no time here).
    """
    from embody.report.stamp import current_report, source_digest, stamp_report
    from embody.store.artifacts import ArtifactStore

    try:
        text = ArtifactStore(store_root).read_manifest_text(run_name)
    except OSError:
        text = None
    digest = source_digest(text=text) if text else ""
    out = Path(out_dir) if out_dir is not None else Path("reports") / run_name
    if reuse and digest:
        current = current_report(out, digest)
        if current is not None:
            return current
    from embody.report.build import default_out_dir, write_report
    from embody.report.reader import collect

    out = Path(out_dir) if out_dir is not None else default_out_dir(run_name)
    (out / ".embody-report-source").unlink(missing_ok=True)  # no stamp on a half-written one
    paths = write_report(collect(store_root, run_name), out)
    if digest:
        stamp_report(out, digest)
    return paths
