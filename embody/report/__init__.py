"""Reports and exports: the paper's tables, figures, an offline HTML page, a trajectory library.

`build_report(store_root, run)` is what `embody run` calls at the end; `write_report(data, dir)`
does the same from in-memory `RunData` (e.g. DataFrames built in a notebook).
"""

from __future__ import annotations

from pathlib import Path

from embody.report.build import ReportPaths, default_out_dir, write_report
from embody.report.reader import collect, latest_run
from embody.report.data import RunData
from embody.report.library import Trajectory, export_library
from embody.report.tables import Table

__all__ = ["ReportPaths", "RunData", "Table", "Trajectory", "build_report", "collect",
           "export_library", "latest_run", "write_report"]


def build_report(store_root: str | Path, run_name: str,
                 out_dir: str | Path | None = None) -> ReportPaths:
    """Write the report of `run_name` (default folder `./reports/<run_name>`)."""
    data = collect(store_root, run_name)
    return write_report(data, out_dir if out_dir is not None else default_out_dir(run_name))
