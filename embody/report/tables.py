"""A report table and its four renderings (CSV, Markdown, booktabs LaTeX, HTML).

The CSV keeps ten significant digits (for machines, without binary float noise such as
0.30000000000000004); the other three share one cell formatter
so the README, the paper and the HTML page show identical digits.
"""

from __future__ import annotations

import html
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

_LATEX_SPECIALS = {
    "\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
    "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
}
_LATEX_RE = re.compile("|".join(re.escape(k) for k in _LATEX_SPECIALS))
# Non-ASCII symbols the tables use, mapped to plain LaTeX so pdflatex needs no unicode setup.
_LATEX_SYMBOLS = {"Δ": r"$\Delta$", "λ": r"$\lambda$", "±": r"$\pm$", "°": r"$^\circ$"}


def latex_escape(text: str) -> str:
    """Escape LaTeX specials, then map the few non-ASCII symbols to math-mode equivalents."""
    out = _LATEX_RE.sub(lambda m: _LATEX_SPECIALS[m.group(0)], text)
    for sym, tex in _LATEX_SYMBOLS.items():
        out = out.replace(sym, tex)
    return out


def format_cell(value: Any) -> str:
    """One number format for every rendering: blanks for missing, sci notation for tiny values."""
    if value is None or value is pd.NA:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isnan(v):
            return ""
        if v == 0:
            return "0"
        if v.is_integer() and abs(v) < 1e6:
            return str(int(v))
        if abs(v) < 1e-2 or abs(v) >= 1e5:
            return f"{v:.2e}"
        if abs(v) < 1:  # three significant digits: a Pose MSE of 0.0197 must not read "0.02"
            return f"{v:.{2 - math.floor(math.log10(abs(v)))}f}"
        return f"{v:.2f}"
    return str(value)


@dataclass(frozen=True)
class Table:
    """A named table: `frame`'s first column holds the row labels, the rest are values."""

    name: str
    title: str
    frame: pd.DataFrame
    #: BibTeX key of the work the table follows: the LaTeX caption ends in `\cite{key}`
    #: (the report writes the entry to `references.bib`).
    cite: str = ""

    def cells(self) -> list[list[str]]:
        return [[format_cell(v) for v in row] for row in self.frame.itertuples(index=False)]

    @property
    def header(self) -> list[str]:
        return [str(c) for c in self.frame.columns]

    def to_csv(self) -> str:
        # Mixed (object) columns hold floats too: round those cells the same way.
        frame = self.frame.map(lambda v: float(f"{v:.10g}") if isinstance(v, float) else v)
        return frame.to_csv(index=False, lineterminator="\n", float_format="%.10g")

    def to_markdown(self) -> str:
        def row(values: list[str]) -> str:
            return "| " + " | ".join(v.replace("|", "\\|") for v in values) + " |"

        align = [":---"] + ["---:"] * (len(self.header) - 1)
        lines = [row(self.header), "| " + " | ".join(align) + " |"]
        lines += [row(r) for r in self.cells()]
        return "\n".join(lines) + "\n"

    def to_latex(self) -> str:
        """A booktabs `table` environment; compiles with only the booktabs package."""
        spec = "l" + "r" * (len(self.header) - 1)
        cite = rf" (after~\cite{{{self.cite}}})" if self.cite else ""
        body = [" & ".join(latex_escape(c) for c in r) + r" \\" for r in self.cells()]
        return "\n".join([
            r"\begin{table}[t]", r"\centering",
            rf"\caption{{{latex_escape(self.title)}{cite}}}", rf"\label{{tab:{self.name}}}",
            rf"\begin{{tabular}}{{{spec}}}", r"\toprule",
            " & ".join(rf"\textbf{{{latex_escape(h)}}}" for h in self.header) + r" \\",
            r"\midrule", *body, r"\bottomrule", r"\end{tabular}", r"\end{table}", "",
        ])

    def to_html(self) -> str:
        esc = html.escape
        head = "".join(f"<th>{esc(h)}</th>" for h in self.header)
        rows = "".join(
            "<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in self.cells())
        return (f'<table class="report" id="{esc(self.name)}"><caption>{esc(self.title)}</caption>'
                f"<thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")

    def write(self, out_dir: Path) -> dict[str, Path]:
        """Write `<name>.csv/.md/.tex`; returns the paths by extension."""
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = {}
        for ext, text in (("csv", self.to_csv()), ("md", self.to_markdown()),
                          ("tex", self.to_latex())):
            path = out_dir / f"{self.name}.{ext}"
            path.write_text(text, encoding="utf-8")
            paths[ext] = path
        return paths
