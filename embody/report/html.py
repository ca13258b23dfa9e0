"""The static `index.html`: tables inline, links to every file, figures; relative links only.

It is one self-contained page with no scripts, so it opens from disk with no server.
"""

from __future__ import annotations

import html
import os
from pathlib import Path
from typing import Any
from urllib.parse import quote

from embody.report.tables import Table, format_cell

_STYLE = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:1100px;color:#222}
table.report{border-collapse:collapse;margin:1em 0}
table.report caption{font-weight:bold;text-align:left;padding:.3em 0}
table.report th,table.report td{border-top:1px solid #ccc;padding:.25em .6em;text-align:right}
table.report th:first-child,table.report td:first-child{text-align:left}
table.report thead th{border-bottom:2px solid #444}
figure{display:inline-block;margin:.5em}
figure img{max-width:520px;border:1px solid #ddd}
.failed{color:#a00}
"""


def _rel(path: Path, root: Path) -> str:
    """A relative URL (percent-encoded) from the page to `path`."""
    return quote(Path(os.path.relpath(path, root)).as_posix())


def _link(path: Path, root: Path, text: str | None = None) -> str:
    href = html.escape(_rel(path, root), quote=True)
    return f'<a href="{href}">{html.escape(text or path.name)}</a>'


def render_index(out_dir: Path, *, run: str, tables: dict[str, tuple[Table, dict[str, Path]]],
                 figures: dict[str, list[Path]], summary: dict[str, Any],
                 files: list[Path], failures: list[tuple[str, str]]) -> Path:
    """Write `out_dir/index.html`; every href/src is relative to `out_dir`."""
    esc = html.escape
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>embody report: {esc(run)}</title><style>{_STYLE}</style></head><body>",
             f"<h1>embody report: {esc(run)}</h1>"]
    parts.append("<h2>Tables</h2>")
    for table, paths in tables.values():
        parts.append(table.to_html())
        parts.append("<p>" + " · ".join(_link(p, out_dir, ext) for ext, p in paths.items())
                     + "</p>")
    if failures:
        parts.append("<h2>Failed sequences</h2><ul>")
        parts += [f'<li class="failed">{esc(sid)}: {esc(err)}</li>' for sid, err in failures]
        parts.append("</ul>")
    for section, paths in figures.items():
        if not paths:
            continue
        parts.append(f"<h2>{esc(section)}</h2>")
        for p in paths:
            src = esc(_rel(p, out_dir), quote=True)
            parts.append(f'<figure><a href="{src}"><img src="{src}" alt="{esc(p.stem)}"></a>'
                         f"<figcaption>{esc(p.stem)}</figcaption></figure>")
    parts.append("<h2>Summary</h2><table class=\"report\" id=\"summary\"><tbody>")
    parts += [f"<tr><td>{esc(k)}</td><td>{esc(format_cell(v))}</td></tr>"
              for k, v in summary.items()]
    parts.append("</tbody></table>")
    parts.append("<h2>Files</h2><ul>")
    parts += [f"<li>{_link(p, out_dir)}</li>" for p in files]
    parts.append("</ul>")
    parts.append("</body></html>\n")
    path = out_dir / "index.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
