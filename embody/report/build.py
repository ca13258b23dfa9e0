"""Write a run's report directory: tables, `sequences.csv`, `summary.json`, figures, index.html."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from embody.csvsafe import csv_safe
from embody.report import assemble, figures
from embody.report.data import RunData
from embody.report.html import render_index
from embody.report.library import safe_name
from embody.report.tables import Table


@dataclass(frozen=True)
class ReportPaths:
    """Where everything of one report was written."""

    out_dir: Path
    index: Path
    summary: Path
    sequences: Path
    tables: dict[str, dict[str, Path]] = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)


def default_out_dir(run_name: str) -> Path:
    """`./reports/<run>` relative to the working directory, like the store's default."""
    return Path("reports") / run_name


def _figures(data: RunData, out_dir: Path) -> dict[str, list[Path]]:
    fig_dir = out_dir / "figures"
    shutil.rmtree(fig_dir, ignore_errors=True)  # ours: no stale figures of an earlier report
    out: dict[str, list[Path]] = {"Collision": [], "Wrist trajectories": [],
                                  "Critic comparison sheets": []}
    if len(data.collision):
        out["Collision"] = [
            figures.collision_energy(data.collision, fig_dir / "collision_energy.png"),
            figures.pose_vs_reduction(data.collision, fig_dir / "pose_vs_reduction.png")]
    for sid, tracks in sorted(data.wrists.items()):
        out["Wrist trajectories"].append(figures.wrist_tracks(
            tracks, data.wrist_fps[sid], fig_dir / "wrists" / f"{safe_name(sid)}.png", title=sid))
    for sid, png in sorted(data.sheets.items()):
        dst = fig_dir / "sheets" / f"{safe_name(sid)}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(png)
        out["Critic comparison sheets"].append(dst)
    return out


def _previews(data: RunData, out_dir: Path) -> list[Path]:
    """The render stage's animated previews, linked from the page (videos are not images)."""
    paths = []
    for sid, (blob, suffix) in sorted(data.previews.items()):
        dst = out_dir / "figures" / "previews" / f"{safe_name(sid)}{suffix}"
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(blob)
        paths.append(dst)
    return paths


def write_report(data: RunData, out_dir: str | Path) -> ReportPaths:
    """Write every report file for `data` under `out_dir` (created if needed)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tables: dict[str, Table] = {}
    if len(data.collision) or data.ablation:
        tables["table1_collision"] = assemble.table1(data)
        tables["table2_ablation"] = assemble.table2(data)
    if len(data.retarget) or data.refine:
        tables["table3_retargeting"] = assemble.table3(data)
    written = {name: t.write(out_dir) for name, t in tables.items()}

    sequences = out_dir / "sequences.csv"
    csv_safe(data.per_sequence()).to_csv(sequences, index=False, lineterminator="\n")
    summary = assemble.summary(data, tables)
    summary_path = out_dir / "summary.json"
    summary_path.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")

    figs = _figures(data, out_dir)
    previews = _previews(data, out_dir)
    index = render_index(out_dir, run=data.name,
                         tables={n: (tables[n], written[n]) for n in tables},
                         figures=figs, summary=summary,
                         files=[sequences, summary_path, *previews],
                         failures=data.failures)
    return ReportPaths(out_dir=out_dir, index=index, summary=summary_path, sequences=sequences,
                       tables=written, figures=[p for ps in figs.values() for p in ps])
