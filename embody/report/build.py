"""Write a run's report directory: tables, `sequences.csv`, `summary.json`, figures, index.html."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from embody.report import assemble, figures
from embody.report.paths import ReportPaths
from embody.report.data import RunData
from embody.report.html import render_index
from embody.report.library import safe_name
from embody.report.tables import Table


def default_out_dir(run_name: str) -> Path:
    """`./reports/<run>` relative to the working directory, like the store's default."""
    return Path("reports") / run_name


def _figures(data: RunData, out_dir: Path) -> tuple[dict[str, list[Path]],
                                                    dict[str, dict[str, Path]]]:
    """(section → figures shown on the page, sequence id → {"sheet"|"wrists"|"preview": path})."""
    fig_dir = out_dir / "figures"
    shutil.rmtree(fig_dir, ignore_errors=True)  # ours: no stale figures of an earlier report
    out: dict[str, list[Path]] = {"Collision": [], "Wrist trajectories": [],
                                  "Critic comparison sheets": []}
    links: dict[str, dict[str, Path]] = {}
    if len(data.collision):
        out["Collision"] = [
            figures.collision_energy(data.collision, fig_dir / "collision_energy.png"),
            figures.pose_vs_reduction(data.collision, fig_dir / "pose_vs_reduction.png")]
    for sid, tracks in sorted(data.wrists.items()):
        path = figures.wrist_tracks(tracks, data.wrist_fps[sid],
                                    fig_dir / "wrists" / f"{safe_name(sid)}.png", title=sid)
        out["Wrist trajectories"].append(path)
        links.setdefault(sid, {})["wrists"] = path
    for sid, png in sorted(data.sheets.items()):
        dst = fig_dir / "sheets" / f"{safe_name(sid)}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(png)
        out["Critic comparison sheets"].append(dst)
        links.setdefault(sid, {})["sheet"] = dst
    for sid, (blob, suffix) in sorted(data.previews.items()):
        dst = fig_dir / "previews" / f"{safe_name(sid)}{suffix}"
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(blob)
        links.setdefault(sid, {})["preview"] = dst
    return out, links


def tables_of(data: RunData) -> dict[str, Table]:
    """The report's tables in page order: the verdicts first, Table II only with its rows."""
    tables: dict[str, Table] = {"verdicts": assemble.verdicts_table(data)}
    if len(data.collision) or data.ablation:
        tables["table1_collision"] = assemble.table1(data)
    if data.ablation:  # without `--ablation` there is no ablation to show
        tables["table2_ablation"] = assemble.table2(data)
    if len(data.retarget) or data.refine:
        tables["table3_retargeting"] = assemble.table3(data)
    return tables


def write_report(data: RunData, out_dir: str | Path) -> ReportPaths:
    """Write every report file for `data` under `out_dir` (created if needed)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.glob("table*_*.*"):  # e.g. Table II of an earlier --ablation report
        stale.unlink()
    tables = tables_of(data)
    written = {name: t.write(out_dir) for name, t in tables.items()}

    sequences = out_dir / "sequences.csv"
    per_sequence = data.per_sequence()
    per_sequence.to_csv(sequences, index=False, lineterminator="\n", float_format="%.10g")
    summary = assemble.summary(data, tables)
    summary_path = out_dir / "summary.json"
    summary_path.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")

    figs, links = _figures(data, out_dir)
    if len(data.retarget) and "wrist_pos_err_mm" in data.retarget:
        worst = data.retarget["wrist_pos_err_mm"].sort_values(ascending=False, kind="stable")
        top = [links[s]["sheet"] for s in worst.index if "sheet" in links.get(s, {})][:4]
        if top:  # shown inline, full width; every other sheet is linked from its table row
            figs[f"Comparison sheets of the {len(top)} sequences with the largest IK wrist "
                 "error"] = top
    index = render_index(out_dir, run=data.name,
                         tables={n: (tables[n], written[n]) for n in tables},
                         figures=figs, summary=summary, files=[sequences, summary_path],
                         failures=data.failures, sequences=per_sequence, links=links,
                         figure_rule=data.figure_rule)
    return ReportPaths(out_dir=out_dir, index=index, summary=summary_path, sequences=sequences,
                       tables=written, figures=[p for ps in figs.values() for p in ps])
