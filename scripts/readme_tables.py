#!/usr/bin/env python
"""Regenerate the README excerpt of Tables I–III from a run's report directory.

    python scripts/readme_tables.py reports/default            # print the excerpt
    python scripts/readme_tables.py reports/default --write README.md
    python scripts/readme_tables.py reports/synth-n24-s0.unitree_h1 --write README.md --block tables-h1

The excerpt (Markdown tables, the robot's note, and for the main block one line per metric)
goes between the markers `<!-- <block>:start -->` and `<!-- <block>:end -->` (default block
`tables`); `--write` replaces what is between them. One block per robot.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

START, END = "<!-- tables:start -->", "<!-- tables:end -->"  # the main (G1) block
TABLES = (
    ("verdicts", "Verdicts: processed ok, export-valid, critic-accepted, physics-valid"),
    ("table1_collision", "Table I: self-collision mitigation"),
    ("table2_ablation", "Table II: loss-term ablation"),
    ("table3_retargeting", "Table III: retargeting fidelity, IK-only vs refined"),
    ("table3_physics", "Table III (physics): the final trajectory replayed in MuJoCo"),
)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout, too
from embody.report.definitions import METRICS, VERDICT_DEFINITIONS, robot_note  # noqa: E402  (one source for page and README)


def markers(block: str = "tables") -> tuple[str, str]:
    return f"<!-- {block}:start -->", f"<!-- {block}:end -->"


def excerpt(report_dir: Path, block: str = "tables", definitions: bool = True) -> str:
    """The Markdown between the markers (markers included)."""
    start, end = markers(block)
    parts = [start, ""]
    for name, title in TABLES:
        md = report_dir / f"{name}.md"
        if md.is_file():
            parts += [f"**{title}** (run `{report_dir.name}`)", "", md.read_text().rstrip(), ""]
    try:  # the robot the run used (summary.json), else the default run name's suffix
        robot = str(json.loads((report_dir / "summary.json").read_text()).get("robot") or "")
    except (OSError, ValueError):
        robot = ""
    robot = robot or report_dir.name.rsplit(".", 1)[-1]
    if robot_note(robot):
        parts += [f"Robot: {robot_note(robot)}", ""]
    if definitions:
        parts += ["Metrics:", ""]
        parts += [f"- **{name}**: {text}" for name, text in (*VERDICT_DEFINITIONS, *METRICS)]
        parts += [""]
    parts += [end]
    return "\n".join(parts)


def replace_between(text: str, block: str, name: str = "tables") -> str:
    start, end = markers(name)
    if start not in text or end not in text:
        raise SystemExit(f"markers {start} / {end} not found")
    head, rest = text.split(start, 1)
    return head + block + rest.split(end, 1)[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report_dir", nargs="?", default="reports/default", type=Path)
    ap.add_argument("--write", type=Path, help="file whose marked block is replaced in place")
    ap.add_argument("--block", default="tables",
                    help="marker name (one block per robot); only `tables` lists the metrics")
    args = ap.parse_args(argv)
    if not any((args.report_dir / f"{n}.md").is_file() for n, _ in TABLES):
        print(f"no tables in {args.report_dir} (run `embody report` first)", file=sys.stderr)
        return 2
    block = excerpt(args.report_dir, args.block, definitions=args.block == "tables")
    if args.write:
        args.write.write_text(replace_between(args.write.read_text(), block, args.block))
    else:
        print(block)
    return 0


if __name__ == "__main__":
    sys.exit(main())
