"""The static `index.html`: verdicts, tables with definitions, every sequence, figures.

One self-contained page with relative links only, so it opens from disk with no server. Its one
small script sorts the per-sequence table by a clicked header; without scripts the page is
complete, just unsorted. Figures are full width and link to themselves (click: natural size).
"""

from __future__ import annotations

import html
import math
import os
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pandas as pd

from embody.report.definitions import (COLUMNS, METRICS, PAPER, VERDICT_DEFINITIONS, paper_citation,
                                       robot_note)
from embody.report.tables import Table, format_cell

_STYLE = """
*{box-sizing:border-box}
body{font-family:system-ui,sans-serif;margin:0 auto;padding:1.5em 2em;max-width:1600px;
     color:#222;overflow-wrap:anywhere}
h1{margin-top:0}
table.report{border-collapse:collapse;margin:1em 0;max-width:100%;font-size:.85em}
.scroll{overflow-x:auto;max-width:100%}
table.report caption{font-weight:bold;text-align:left;padding:.3em 0}
table.report th,table.report td{border-top:1px solid #ccc;padding:.25em .4em;text-align:right;
     overflow-wrap:normal}
table.report th:first-child,table.report td:first-child{text-align:left}
table.report thead th{border-bottom:2px solid #444;vertical-align:bottom}
table.report tbody th{text-align:left;background:#f3f3f3;padding-top:.6em}
table.sortable thead th{cursor:pointer}
table.sortable thead th:hover{background:#eef}
table.report td.text{text-align:left;min-width:10em;max-width:24em;overflow-wrap:anywhere}
#sequences td:first-child{overflow-wrap:anywhere;min-width:7em;max-width:16em}
#sequences th:nth-child(2){text-align:left}
table.report td.yes{color:#070} table.report td.no{color:#a00}
figure{margin:1em 0}
figure img{display:block;max-width:100%;height:auto;border:1px solid #ddd}
figcaption{font-size:.9em;color:#555}
dl.defs dt{font-weight:bold;margin-top:.4em} dl.defs dd{margin-left:1.5em}
.note{color:#555;font-size:.95em}
.failed{color:#a00}
"""

#: Click a header to sort the per-sequence table (numbers numerically, blanks last).
_SORT = """<script>
document.querySelectorAll('table.sortable').forEach(t => {
  t.querySelectorAll('thead th').forEach((th, col) => th.addEventListener('click', () => {
    const asc = th.dataset.dir !== 'asc';
    t.querySelectorAll('thead th').forEach(h => delete h.dataset.dir);
    th.dataset.dir = asc ? 'asc' : 'desc';
    const key = r => { const c = r.cells[col]; const v = c.dataset.v ?? c.textContent.trim();
      const n = parseFloat(v); return v === '' ? null : (isNaN(n) ? v : n); };
    const rows = [...t.tBodies[0].rows].sort((a, b) => {
      const x = key(a), y = key(b);
      if (x === null) return 1; if (y === null) return -1;
      const c = (typeof x === 'number' && typeof y === 'number') ? x - y : String(x).localeCompare(String(y));
      return asc ? c : -c; });
    rows.forEach(r => t.tBodies[0].appendChild(r));
  }));
});
</script>"""

#: Summary key prefix → section heading of the formatted summary.
_SECTIONS = (("sequences.", "Sequences"), ("verdicts.", "Verdicts"),
             ("collision.", "Collision mitigation (Table I)"),
             ("retarget.ik_only.", "IK only (Table III)"), ("retarget.refined.", "Refined"),
             ("retarget.", "Final trajectories"))
_UNITS = {"_mm": " (mm)", "_deg": " (deg)", "_pct": " (%)", "_s": " (s)"}


def _rel(path: Path, root: Path) -> str:
    """A relative URL (percent-encoded) from the page to `path`."""
    return quote(Path(os.path.relpath(path, root)).as_posix())


def _link(path: Path, root: Path, text: str | None = None) -> str:
    href = html.escape(_rel(path, root), quote=True)
    return f'<a href="{href}">{html.escape(text or path.name)}</a>'


def _figure(path: Path, root: Path, caption: str) -> str:
    src = html.escape(_rel(path, root), quote=True)
    return (f'<figure><a href="{src}" title="open at full size"><img src="{src}" '
            f'alt="{html.escape(caption, quote=True)}"></a>'
            f"<figcaption>{html.escape(caption)} (click for full size)</figcaption></figure>")


def _label(key: str) -> str:
    """`wrist_pos_mean_mm` → "wrist pos mean (mm)"."""
    for suffix, unit in _UNITS.items():
        if key.endswith(suffix):
            return key[: -len(suffix)].replace("_", " ").replace(".", " · ") + unit
    return key.replace("_", " ").replace(".", " · ")


def summary_table(summary: dict[str, Any]) -> str:
    """`summary.json` as a sectioned two-column table with readable names and units."""
    esc = html.escape
    left = dict(summary)
    parts = ['<table class="report" id="summary"><caption>Summary (summary.json)</caption>']
    head = [(k, left.pop(k)) for k in ("run", "robot") if k in left]
    if head:
        parts.append("<tbody>" + "".join(f"<tr><td>{k}</td><td>{esc(str(v))}</td></tr>"
                                          for k, v in head) + "</tbody>")
    for prefix, heading in _SECTIONS:
        keys = [k for k in left if k.startswith(prefix)]
        if not keys:
            continue
        parts.append(f'<tbody><tr><th colspan="2">{esc(heading)}</th></tr>')
        for k in keys:
            parts.append(f"<tr><td>{esc(_label(k[len(prefix):]))}</td>"
                         f"<td>{esc(format_cell(left.pop(k)))}</td></tr>")
        parts.append("</tbody>")
    if left:
        parts.append('<tbody><tr><th colspan="2">Other</th></tr>')
        parts += [f"<tr><td>{esc(_label(k))}</td><td>{esc(format_cell(v))}</td></tr>"
                  for k, v in left.items()]
        parts.append("</tbody>")
    parts.append("</table>")
    return "".join(parts)


def _verdict_cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return '<td data-v=""></td>'
    yes = bool(value)
    return f'<td class="{"yes" if yes else "no"}" data-v="{int(yes)}">{"yes" if yes else "no"}</td>'


def sequence_table(frame: pd.DataFrame, links: dict[str, dict[str, Path]], root: Path) -> str:
    """One row per sequence: verdicts, headline metrics and links to its figures."""
    esc = html.escape
    metric_cols = {h: c for h, (c, _) in COLUMNS.items() if c in frame}
    head = (["Sequence", "Text", "Processed ok", "Export-valid", "Critic-accepted", "Physics-valid"]
            + list(metric_cols) + ["Sheet", "Preview", "Plots"])
    parts = ['<div class="scroll"><table class="report sortable" id="sequences">'
             "<caption>Every sequence (click a header to sort)</caption><thead><tr>"
             + "".join(f"<th>{esc(h)}</th>" for h in head) + "</tr></thead><tbody>"]
    for row in frame.to_dict("records"):
        sid = str(row["id"])
        cells = [f'<td id="seq-{esc(sid, quote=True)}">{esc(sid)}</td>',
                 f'<td class="text">{esc(str(row.get("text") or ""))}</td>']
        cells += [_verdict_cell(row.get(v)) for v in
                  ("processed_ok", "export_valid", "critic_accepted", "physics_valid")]
        for col in metric_cols.values():
            value = row.get(col)
            num = "" if value is None or (isinstance(value, float) and math.isnan(value)) \
                else f"{float(value):.6g}"
            cells.append(f'<td data-v="{num}">{esc(format_cell(value))}</td>')
        mine = links.get(sid, {})
        for kind, text in (("sheet", "sheet"), ("preview", "preview")):
            cells.append(f"<td>{_link(mine[kind], root, text)}</td>" if kind in mine
                         else '<td data-v="">–</td>')
        plots = [_link(mine[kind], root, kind) for kind in ("wrists", "location", "physics") if kind in mine]
        cells.append(f"<td>{' · '.join(plots)}</td>" if plots else '<td data-v="">–</td>')
        parts.append(f'<tr class="{"" if row.get("processed_ok") else "failed"}">'
                     + "".join(cells) + "</tr>")
    parts.append("</tbody></table></div>")
    return "".join(parts)


def _definitions(items: Any) -> str:
    esc = html.escape
    return ('<dl class="defs">' + "".join(f"<dt>{esc(n)}</dt><dd>{esc(t)}</dd>" for n, t in items)
            + "</dl>")


def render_index(out_dir: Path, *, run: str, tables: dict[str, tuple[Table, dict[str, Path]]],
                 figures: dict[str, list[Path]], summary: dict[str, Any],
                 files: list[Path], failures: list[tuple[str, str]],
                 sequences: pd.DataFrame | None = None,
                 links: dict[str, dict[str, Path]] | None = None,
                 figure_rule: str = "", robot: str = "") -> Path:
    """Write `out_dir/index.html`; every href/src is relative to `out_dir`."""
    esc = html.escape
    links = links or {}
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
             f'<meta name="viewport" content="width=device-width, initial-scale=1">'
             f"<title>embody report: {esc(run)}</title><style>{_STYLE}</style></head><body>",
             f"<h1>embody report: {esc(run)}</h1>",
             *([f'<p class="note">Robot: {esc(robot)}.</p>'] if robot else []),
             '<p class="note">Tables I–III follow the paper <a href="#ref-paper">[1]</a>. Its '
             "published figures are in Table I's “Paper (reported)” column; every other number "
             "is computed from this run's stored results.</p>"]
    parts.append("<h2>Tables</h2>")
    for name, (table, paths) in tables.items():
        parts.append(f'<div class="scroll">{table.to_html()}</div>')
        parts.append("<p>" + " · ".join(_link(p, out_dir, ext) for ext, p in paths.items())
                     + "</p>")
        if name == "verdicts":
            parts.append(_definitions(VERDICT_DEFINITIONS))
        if name == "table3_retargeting" and robot_note(robot):
            parts.append(f'<p class="note" id="robot-note"><b>Robot {esc(robot)}:</b> '
                         f"{esc(robot_note(robot))}</p>")
        if name == "table2_ablation":
            parts.append('<p class="note">Table II: every setting is computed in the same '
                         "<code>embody report --ablation</code> flow (its own store, the run's "
                         "workers, collision step only), so its times are measured the same way "
                         "for every row; they are not comparable with Table I's runtime, which "
                         "was measured inside the full pipeline.</p>")
    parts.append("<h2>Metric definitions</h2>")
    parts.append(_definitions(METRICS))
    if sequences is not None and len(sequences):
        parts.append("<h2>Sequences</h2>")
        rule = figure_rule or "Every finished sequence has its figures."
        parts.append(f'<p class="note">{esc(rule)} Failed sequences are listed with '
                     "their error below.</p>")
        parts.append(_definitions((h, d) for h, (_, d) in COLUMNS.items()))
        parts.append(sequence_table(sequences, links, out_dir))
    if failures:
        parts.append("<h2>Failed sequences</h2><ul>")
        parts += [f'<li class="failed">{esc(sid)}: {esc(err)}</li>' for sid, err in failures]
        parts.append("</ul>")
    linked = ("Critic comparison sheets", "Wrist trajectories", "Location error")
    for section, paths in figures.items():
        if not paths or (section in linked and sequences is not None):
            continue  # every per-sequence figure is reached from the sequence table
        parts.append(f"<h2>{esc(section)}</h2>")
        parts += [_figure(p, out_dir, p.stem) for p in paths]
    parts.append("<h2>Summary</h2>")
    parts.append(summary_table(summary))
    parts.append("<h2>Files</h2><ul>")
    parts += [f"<li>{_link(p, out_dir)}</li>" for p in files]
    parts.append("</ul>")
    parts.append("<h2>References</h2>")
    parts.append(f'<ol class="references"><li id="ref-paper">{esc(paper_citation())} '
                 f"(BibTeX key <code>{esc(PAPER['key'])}</code>)</li></ol>")
    parts.append(_SORT)
    parts.append("</body></html>\n")
    path = out_dir / "index.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
