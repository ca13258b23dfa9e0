#!/usr/bin/env python
"""Regenerate the README excerpt of Tables I–III from a run's report directory.

    python scripts/readme_tables.py reports/default            # print the excerpt
    python scripts/readme_tables.py reports/default --write README.md

The excerpt (Markdown tables plus one line per metric) goes between the markers
`<!-- tables:start -->` and `<!-- tables:end -->`; `--write` replaces what is between them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

START, END = "<!-- tables:start -->", "<!-- tables:end -->"
TABLES = (
    ("verdicts", "Verdicts: processed ok, export-valid, critic-accepted"),
    ("table1_collision", "Table I: self-collision mitigation"),
    ("table2_ablation", "Table II: loss-term ablation"),
    ("table3_retargeting", "Table III: retargeting fidelity, IK-only vs refined"),
)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout, too
from embody.report.definitions import METRICS, VERDICT_DEFINITIONS  # noqa: E402  (one source for page and README)


def excerpt(report_dir: Path) -> str:
    """The Markdown between the markers (markers included)."""
    parts = [START, ""]
    for name, title in TABLES:
        md = report_dir / f"{name}.md"
        if md.is_file():
            parts += [f"**{title}** (run `{report_dir.name}`)", "", md.read_text().rstrip(), ""]
    parts += ["Metrics:", ""]
    parts += [f"- **{name}**: {text}" for name, text in (*VERDICT_DEFINITIONS, *METRICS)]
    parts += ["", END]
    return "\n".join(parts)


def replace_between(text: str, block: str) -> str:
    if START not in text or END not in text:
        raise SystemExit(f"markers {START} / {END} not found")
    head, rest = text.split(START, 1)
    return head + block + rest.split(END, 1)[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report_dir", nargs="?", default="reports/default", type=Path)
    ap.add_argument("--write", type=Path, help="file whose marked block is replaced in place")
    args = ap.parse_args(argv)
    if not any((args.report_dir / f"{n}.md").is_file() for n, _ in TABLES):
        print(f"no tables in {args.report_dir} (run `embody report` first)", file=sys.stderr)
        return 2
    block = excerpt(args.report_dir)
    if args.write:
        args.write.write_text(replace_between(args.write.read_text(), block))
    else:
        print(block)
    return 0


if __name__ == "__main__":
    sys.exit(main())
