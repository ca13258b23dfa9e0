"""How far the 50 Hz export moved each sequence away from its plain resample (issue 14, fidelity).

Why: the control-rate Table III is measured on the exported array. When an interpolated sample
touches (MuJoCo) and `bridge_contacts` finds no local bridge, `separate` pushes it apart with a
hat wide enough for the velocity budget: on synth seq 17 (s9-ikwin run, 21:12) 3 touching
samples (64, 69, 72) moved the arms by up to 109.6° over 93 samples and its refined 50 Hz
location went 32.5 → 50.6 mm. This reads a stored run (no solve): for every sequence the
exported `q_control` (metrics artifact) against the refine/retarget q resampled, clipped and
velocity-clamped exactly as `control_trajectory` does before its repair, and MuJoCo's verdict
on that resample.

Usage: python benchmarks/export_drift.py [--store DIR] [--run NAME]
Ends with `RESULT seqs=… touching_seqs=… touching_samples=… moved_seqs=… max_drift_deg=… worst=…`
(moved: any joint > 1° from the resample).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from embody.config import Config
from embody.retarget.control import BOX_MARGIN, VELOCITY_MARGIN, _Separator
from embody.retarget.limits import clamp_velocity, resample
from embody.robot import load_robot
from embody.store.artifacts import ArtifactStore


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--store", default="embody-store")
    ap.add_argument("--run", default="synth-n24-s0.unitree_g1_dex3")
    ap.add_argument("--moved-deg", type=float, default=1.0)
    args = ap.parse_args()
    store = ArtifactStore(args.store)
    manifest = json.loads((Path(args.store) / "runs" / args.run / "manifest.json").read_text())
    robot = robot_cfg = None
    sep = None
    touching_seqs = touching = moved = 0
    worst, worst_deg = "-", 0.0
    for seq, info in sorted(manifest["sequences"].items()):
        steps = info.get("steps") or {}
        if "metrics" not in steps:
            continue
        src = "refine" if "refine" in steps else "retarget"
        art = store.read(src, steps[src], check=False)
        ret = store.read("retarget", steps["retarget"], check=False)
        if robot is None or art.info["config"]["robot"] != robot_cfg:
            robot_cfg = art.info["config"]["robot"]
            robot = load_robot(type(Config().robot).model_validate_json(robot_cfg))
            sep = _Separator(robot)
        fps, rate = float(ret.attrs["fps"]), float(ret.attrs["control_rate_hz"])
        q = np.asarray(art.arrays["q"], np.float64)
        q = q[-1] if q.ndim == 3 else q  # refine: (rounds, T, n), the last one chosen
        qc = resample(q, fps, rate)
        qc = np.clip(qc, robot.lower + BOX_MARGIN, robot.upper - BOX_MARGIN)
        qc = clamp_velocity(qc, robot.velocity_limits * (1.0 - VELOCITY_MARGIN), rate)
        exported = np.asarray(store.read("metrics", steps["metrics"], check=False).arrays["q_control"], np.float64)
        bad = [t for t, x in enumerate(qc) if sep.contacts(x, jacobians=False)]
        n = min(len(qc), len(exported))
        drift = np.degrees(np.abs(exported[:n] - qc[:n]).max(axis=1))
        touching_seqs += bool(bad)
        touching += len(bad)
        moved += bool(drift.max() > args.moved_deg)
        if drift.max() > worst_deg:
            worst, worst_deg = seq, float(drift.max())
        print(f"{seq} frames={len(q)} samples={len(exported)} touching={bad} "
              f"max_drift_deg={drift.max():.3f} moved_samples={int((drift > args.moved_deg).sum())}")
    print(f"RESULT seqs={len(manifest['sequences'])} touching_seqs={touching_seqs} "
          f"touching_samples={touching} moved_seqs={moved} max_drift_deg={worst_deg:.3f} worst={worst}")


if __name__ == "__main__":
    main()
