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
    ("table1_collision", "Table I: self-collision mitigation"),
    ("table2_ablation", "Table II: loss-term ablation"),
    ("table3_retargeting", "Table III: retargeting fidelity, IK-only vs refined"),
)
METRICS = (
    ("Collision energy", "volumetric self-collision energy L_col (Eq. 1): mean over frames of "
     "squared penetration depths of body vertices inside other body parts' convex volumes."),
    ("Improved sequences", "share of colliding sequences whose energy went down; sequences with "
     "zero energy before are counted as \"no collision\", not as successes."),
    ("Collision reduction", "(before − after) / before × 100 per sequence, then median or mean."),
    ("Pose MSE vs. original", "mean over frames of the squared change of the axis-angle pose."),
    ("ΔAccel MSE", "change of the mean squared second difference of the pose (jerkiness added)."),
    ("Runtime per sequence", "wall-clock seconds of the collision optimisation per sequence."),
    ("Paper (reported)", "the paper's own figures, for comparison; blank where it gives none."),
    ("N / Succ. / Red.", "Table II: sequences, improved share, median reduction per setting."),
    ("Wrist pos. error", "robot wrist vs. the human reference in the robot torso frame (mm), "
     "mean and 95th percentile over frames."),
    ("Wrist rot. error", "geodesic angle between robot and reference wrist orientation (deg)."),
    ("DTW wrist error", "wrist error after dynamic time warping, robust to timing drift."),
    ("Limit / velocity violations", "frames outside joint position / velocity limits (target 0)."),
    ("Self-collision frames", "frames with a penetrating MuJoCo contact between non-adjacent "
     "robot bodies (target 0)."),
    ("Rounds / Accepted", "critic refinement rounds used, and the share the critic accepted."),
)


def excerpt(report_dir: Path) -> str:
    """The Markdown between the markers (markers included)."""
    parts = [START, ""]
    for name, title in TABLES:
        md = report_dir / f"{name}.md"
        if md.is_file():
            parts += [f"**{title}** (run `{report_dir.name}`)", "", md.read_text().rstrip(), ""]
    parts += ["Metrics:", ""]
    parts += [f"- **{name}**: {text}" for name, text in METRICS]
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
