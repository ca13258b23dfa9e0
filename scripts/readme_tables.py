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
    ("Collision energy", "volumetric self-collision energy L_col (Eq. 1): mean over frames of the "
     "squared depths of body vertices inside other body parts' convex volumes; statistics over "
     "the sequences that collided before mitigation."),
    ("Improved sequences", "colliding sequences whose energy went down (n/N and %); sequences with "
     "zero energy before count as \"no collision\", neither success nor failure."),
    ("Collision reduction", "(before − after) / before × 100 per sequence, then median or mean."),
    ("Pose MSE vs. original", "mean over frames of the squared norm of the pose change "
     "(axis-angle, all joints); median over sequences."),
    ("ΔAccel MSE", "mean squared second difference of the pose after minus before: the jerkiness "
     "the optimisation added (negative = smoother); median over sequences."),
    ("Runtime per sequence", "wall-clock seconds of the collision optimisation, mean."),
    ("Paper (reported)", "the paper's own figures for comparison; blank where it reports none."),
    ("Table II", "the same metrics per loss setting: N colliding sequences, Succ. = improved %, "
     "Red. = median reduction %, medians of Pose/ΔAccel MSE, mean time."),
    ("Wrist pos. mean / p95", "distance between robot and human wrists in the robot torso frame "
     "(mm), both wrists, mean and 95th percentile over frames, averaged over sequences."),
    ("Wrist rot. mean", "geodesic angle between robot and human wrist orientations (deg)."),
    ("DTW wrist", "wrist distance after dynamic time warping (mm): robust to timing drift."),
    ("Limit viol. / Vel. viol.", "(frame, joint) samples outside the joint position / velocity "
     "limits, summed over sequences (target 0)."),
    ("Self-coll. frames", "frames with a penetrating MuJoCo contact between non-adjacent robot "
     "bodies, summed over sequences (target 0)."),
    ("Rounds / Accepted", "critic rounds used (mean) and the share of sequences it accepted."),
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
