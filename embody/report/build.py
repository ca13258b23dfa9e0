"""Write a run's report directory: tables, `sequences.csv`, `summary.json`, figures, index.html."""

from __future__ import annotations

import json
from pathlib import Path

from embody.csvsafe import csv_safe
from embody.report import assemble, drawing, figures
from embody.report.paths import ReportPaths, safe_name
from embody.report.data import RunData
from embody.report.definitions import paper_bibtex
from embody.report.html import render_index
from embody.report.tables import Table


def default_out_dir(run_name: str) -> Path:
    """`./reports/<run>` relative to the working directory, like the store's default."""
    from embody.store.manifest import check_run_name

    return Path("reports") / check_run_name(run_name, "RUN")


#: What a report wrote into its folder: the next report there deletes exactly these files.
_RECORD = ".embody-report.json"


def _forget_previous(out_dir: Path) -> None:
    """Delete the files an earlier report wrote here (no stale figures), and nothing else:
    files it did not record, symlinks and anything outside `out_dir` are left alone."""
    try:
        files = json.loads((out_dir / _RECORD).read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return
    root = out_dir.resolve()
    dirs = set()
    for rel in files if isinstance(files, list) else []:
        path = out_dir / str(rel)
        if path.is_symlink() or not path.is_file() or not path.resolve().is_relative_to(root):
            continue
        path.unlink()
        dirs.update(d for d in path.parents if d.resolve().is_relative_to(root) and d != out_dir)
    for d in sorted(dirs, key=lambda d: len(d.parts), reverse=True):
        try:
            d.rmdir()  # only when empty
        except OSError:
            pass


def _remember(out_dir: Path, paths: list[Path]) -> None:
    rel = sorted({Path(p).relative_to(out_dir).as_posix() for p in paths})
    (out_dir / _RECORD).write_text(json.dumps({"files": rel}, indent=1) + "\n")


def _figures(data: RunData, out_dir: Path, processes: int | None = None
             ) -> tuple[dict[str, list[Path]], dict[str, dict[str, Path]]]:
    """(section → figures shown on the page, sequence id → {"sheet"|"wrists"|"location"|"physics"|"preview":
    path}). The plots are drawn side by side (`drawing.draw`; `processes` as there)."""
    fig_dir = out_dir / "figures"
    out: dict[str, list[Path]] = {"Collision": [], "Wrist trajectories": [],
                                  "Location error": [], "Physics replay": [], "Critic comparison sheets": []}
    links: dict[str, dict[str, Path]] = {}
    jobs: list[drawing.Job] = []
    places: list[tuple[str, str | None, str | None]] = []  # (section, sequence, link name)
    if len(data.collision):
        jobs += [(figures.collision_energy, (data.collision, fig_dir / "collision_energy.png"), {}),
                 (figures.pose_vs_reduction, (data.collision, fig_dir / "pose_vs_reduction.png"),
                  {})]
        places += [("Collision", None, None)] * 2
    for sid, tracks in sorted(data.wrists.items()):
        jobs.append((figures.wrist_tracks, (tracks, data.wrist_fps[sid],
                                            fig_dir / "wrists" / f"{safe_name(sid)}.png"),
                     {"title": sid}))
        places.append(("Wrist trajectories", sid, "wrists"))
    for sid, loc in sorted(data.locations.items()):
        jobs.append((figures.location_error, (loc["err"], loc["landmark"], loc["names"],
                                              loc["fps"],
                                              fig_dir / "location" / f"{safe_name(sid)}.png"),
                     {"title": sid}))
        places.append(("Location error", sid, "location"))
    for sid, phys in sorted(data.physics.items()):
        jobs.append((figures.physics_trace, (phys["torque_ratio"], phys["palm_err_mm"], phys["fps"],
                                             fig_dir / "physics" / f"{safe_name(sid)}.png"),
                     {"title": sid}))
        places.append(("Physics replay", sid, "physics"))
    for path, (section, sid, name) in zip(drawing.draw(jobs, processes), places):
        out[section].append(path)
        if sid is not None:
            links.setdefault(sid, {})[name] = path
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
    if len(data.retarget) or data.refined:
        tables["table3_retargeting"] = assemble.table3(data)
        physics = assemble.table3_physics(data)
        if physics is not None:
            tables["table3_physics"] = physics
    return tables


def write_report(data: RunData, out_dir: str | Path) -> ReportPaths:
    """Write every report file for `data` under `out_dir` (created if needed)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _forget_previous(out_dir)
    tables = tables_of(data)
    written = {name: t.write(out_dir) for name, t in tables.items()}

    sequences = out_dir / "sequences.csv"
    per_sequence = data.per_sequence()
    csv_safe(per_sequence).to_csv(sequences, index=False, lineterminator="\n", float_format="%.10g")
    references = out_dir / "references.bib"  # what the LaTeX tables' \cite keys resolve to
    references.write_text(paper_bibtex(), encoding="utf-8")
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
                         figures=figs, summary=summary,
                         files=[sequences, summary_path, references],
                         failures=data.failures, sequences=per_sequence, links=links,
                         figure_rule=data.figure_rule, robot=data.robot)
    _remember(out_dir, [index, sequences, summary_path, references,
                        *(p for files in written.values() for p in files.values()),
                        *(p for ps in figs.values() for p in ps),
                        *(p for seq in links.values() for p in seq.values())])
    return ReportPaths(out_dir=out_dir, index=index, summary=summary_path, sequences=sequences,
                       tables=written, figures=[p for ps in figs.values() for p in ps])
