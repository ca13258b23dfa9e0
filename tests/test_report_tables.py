"""Table renderings: number formatting, Markdown, booktabs LaTeX (compiled when pdflatex exists)."""

from __future__ import annotations

import math
import subprocess
import sys

import pandas as pd
import pytest

from embody.report.assemble import number
from embody.report.tables import Table, format_cell, latex_escape


@pytest.fixture()
def table() -> Table:
    frame = pd.DataFrame({"Metric": ["Improved sequences (%)", "ΔAccel MSE (median)", "a_b & 50%"],
                          "Before": [math.nan, 1.5e-5, 3], "After": [88.88888, 2.0, 4.25]})
    return Table("t_demo", "Demo: 100% of #1", frame)


def test_format_cell() -> None:
    assert format_cell(math.nan) == "" and format_cell(None) == ""
    assert format_cell(88.8888) == "88.89"
    assert format_cell(6.8e-4) == "6.80e-04"
    # below 1: three significant digits (a median of 0.0197 against a 0.0206 target stays legible)
    assert format_cell(0.019745) == "0.0197" and format_cell(0.5) == "0.500"
    assert format_cell(-0.8234) == "-0.823" and format_cell(0.99949) == "0.999"
    assert format_cell(3.0) == "3" and format_cell(7) == "7"
    assert format_cell(123456.0) == "123456" and format_cell(123456.7) == "1.23e+05"


def test_latex_escape() -> None:
    assert latex_escape(r"a_b & 50% #1 $x {y} ~ ^") == \
        r"a\_b \& 50\% \#1 \$x \{y\} \textasciitilde{} \textasciicircum{}"
    assert latex_escape("ΔAccel") == r"$\Delta$Accel"


def test_number_parses_cells() -> None:
    assert number("8/9 (88.9%)") == 88.9
    assert number(" 21.66 %") == 21.66
    assert number(6.8e-4) == 6.8e-4
    assert math.isnan(number("")) and math.isnan(number(None))


def test_renderings(table: Table, tmp_path) -> None:
    paths = table.write(tmp_path)
    assert set(paths) == {"csv", "md", "tex"}
    back = pd.read_csv(paths["csv"])
    assert back["After"].tolist() == [88.88888, 2.0, 4.25]
    md = paths["md"].read_text().splitlines()
    assert md[0] == "| Metric | Before | After |"
    assert md[2] == "| Improved sequences (%) |  | 88.89 |"
    tex = paths["tex"].read_text()
    for word in (r"\toprule", r"\midrule", r"\bottomrule", r"a\_b \& 50\%", r"$\Delta$Accel",
                 r"Demo: 100\% of \#1", "1.50e-05"):
        assert word in tex
    html = table.to_html()
    assert html.count("<tr>") == 4 and 'id="t_demo"' in html and "a_b &amp; 50%" in html


def test_latex_compiles(table: Table, pdflatex: str, tmp_path) -> None:
    table.write(tmp_path)
    doc = tmp_path / "doc.tex"
    doc.write_text("\\documentclass{article}\\usepackage{booktabs}\\begin{document}"
                   "\\input{t_demo.tex}\\end{document}\n")
    proc = subprocess.run([pdflatex, "-interaction=nonstopmode", "-halt-on-error", "doc.tex"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:]
    assert (tmp_path / "doc.pdf").stat().st_size > 0


def test_report_modules_do_not_import_prefect() -> None:
    code = ("import sys, embody.report, embody.report.reader, embody.cli.report, "
            "embody.cli.export, embody.cli.play; assert 'prefect' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_paper_cited_in_latex_and_html(table: Table, pdflatex: str, tmp_path) -> None:
    """The tables that follow the paper cite it: a `\\cite` that BibTeX resolves from the
    report's `references.bib` to the full reference, and the page's reference list."""
    import dataclasses
    import shutil

    from embody.report.definitions import PAPER, paper_bibtex, paper_citation
    from embody.report.html import render_index

    cited = dataclasses.replace(table, cite=PAPER["key"])
    assert r"\cite{khan2026sign}" in cited.to_latex() and r"\cite" not in table.to_latex()
    cited.write(tmp_path)
    (tmp_path / "references.bib").write_text(paper_bibtex())
    (tmp_path / "doc.tex").write_text(
        "\\documentclass{article}\\usepackage{booktabs}\\begin{document}\\input{t_demo.tex}"
        "\\bibliographystyle{plain}\\bibliography{references}\\end{document}\n")
    bibtex = shutil.which("bibtex")
    if bibtex is None:
        pytest.skip("bibtex is not installed (apt-get install texlive-binaries)")
    for cmd in ([pdflatex, "-interaction=nonstopmode", "-halt-on-error", "doc.tex"],
                [bibtex, "doc"], *[[pdflatex, "-interaction=nonstopmode", "-halt-on-error", "doc.tex"]] * 2):
        proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stdout[-2000:]
    bbl = " ".join((tmp_path / "doc.bbl").read_text().replace("~", " ").split())
    for words in ("N. Khan", "K. Nakadai", "From Sign Language Generation to Humanoid Execution",
                  "Collision Mitigation", "Intelligent Robots and Systems", "2026"):
        assert words in bbl, words
    assert "citation `khan2026sign' on page 1 undefined" not in (tmp_path / "doc.log").read_text().lower()

    page = render_index(tmp_path, run="demo", tables={}, figures={}, summary={}, files=[],
                        failures=[]).read_text()
    assert 'href="#ref-paper">[1]</a>' in page and 'id="ref-paper"' in page
    assert "T. Ashizawa, C. T. Ishi, T. Minato, and K. Nakadai" in page
    assert "Vision–Language Guided Retargeting with Collision Mitigation" in page
    assert paper_citation().startswith("N. Khan, B. Wu, R. Shi, B. Yen")
