"""How far the 50 Hz export moved each sequence away from its plain resample (issue 14, fidelity).

Why: the control-rate Table III is measured on the exported array. When an interpolated sample
touches (MuJoCo) and `bridge_contacts` finds no local bridge, `separate` pushes it apart: before
its trust radii (s11-separate) a hat wide enough for the velocity budget took the push into the
neighbours, and on synth seq 17 (s9-ikwin run, 21:12) 3 touching samples (64, 69, 72) moved the
arms by up to 109.6° over 93 samples and its refined 50 Hz location went 32.5 → 50.6 mm. This
reads a stored run (no solve): for every sequence the exported `q_control` (metrics artifact)
against the refine/retarget q resampled, clipped and velocity-clamped exactly as
`control_trajectory` does before its repair, and MuJoCo's verdict on that resample.

`--recompute`: the export is recomputed from the stored q with the current code
(`control_trajectory_checked`) instead of read, so a change to the repair is measured on the same
stored inputs; `--ref FILE` recomputes it with that copy of `embody/retarget/control.py` instead
(e.g. `git show <commit>:embody/retarget/control.py > /tmp/control_ref.py`): a same-process A/B.
`--refine KEY ...`: these refine artifacts (full keys) instead of a run's manifest (the seq-17
replays of docs/performance.md: 91e3b0…, 91ae1b…); `--refine` alone: every refine artifact in
the store (every run and code version kept there: more touching cases than one run has).

Usage: python benchmarks/export_drift.py [--store DIR] [--run NAME] [--recompute] [--ref FILE]
       [--refine KEY ...]
Ends with `RESULT seqs=… touching_seqs=… touching_samples=… moved_seqs=… max_drift_deg=… worst=…
not_clear=… invalid=… repair_cpu_s=…` (moved: any joint > 1° from the resample; not_clear: the
repair's own flag False, recompute only; invalid: sequences whose export has joint-limit,
velocity or MuJoCo-contact violations; repair_cpu_s: CPU seconds of the recomputes).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _reference import load_reference  # noqa: E402  benchmarks/, the script's own folder

from embody.config import Config  # noqa: E402
from embody.retarget import control  # noqa: E402
from embody.retarget.control import BOX_MARGIN, VELOCITY_MARGIN, _Separator  # noqa: E402
from embody.retarget.limits import clamp_velocity, resample  # noqa: E402
from embody.retarget.validation import validation_counts  # noqa: E402
from embody.robot import load_robot  # noqa: E402
from embody.store.artifacts import ArtifactStore  # noqa: E402

DEFAULT_STORE = Path(__file__).resolve().parent.parent / "embody-store"


def _sequences(store: ArtifactStore, args: argparse.Namespace) -> Iterator[tuple[str, object, float, float, object]]:
    """(name, refine/retarget artifact, fps, control rate, stored export or None) per sequence."""
    if args.refine is not None:
        keys = args.refine or sorted(p.name for p in (Path(args.store) / "artifacts" / "refine").glob("*/*")
                                     if p.is_dir() and len(p.name) == 64)
        for key in keys:
            art = store.read("refine", key, check=False)
            ret = store.read("retarget", art.info["inputs"]["retarget"], check=False)
            yield (f"{art.info.get('sequence', '?')}@{key[:6]}", art, float(ret.attrs["fps"]),
                   float(ret.attrs["control_rate_hz"]), art.arrays["final_q_control"])
        return
    manifest = json.loads((Path(args.store) / "runs" / args.run / "manifest.json").read_text())
    for seq, info in sorted(manifest["sequences"].items()):
        steps = info.get("steps") or {}
        if "metrics" not in steps:
            continue
        src = "refine" if "refine" in steps else "retarget"
        art = store.read(src, steps[src], check=False)
        ret = store.read("retarget", steps["retarget"], check=False)
        exported = store.read("metrics", steps["metrics"], check=False).arrays["q_control"]
        yield seq, art, float(ret.attrs["fps"]), float(ret.attrs["control_rate_hz"]), exported


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--store", default=str(DEFAULT_STORE))
    ap.add_argument("--run", default="synth-n24-s0.unitree_g1_dex3")
    ap.add_argument("--moved-deg", type=float, default=1.0)
    ap.add_argument("--recompute", action="store_true", help="recompute the export with the current code")
    ap.add_argument("--ref", default=None, help="recompute with this copy of retarget/control.py instead")
    ap.add_argument("--refine", nargs="*", default=None, help="refine artifact keys instead of a run (none: all)")
    args = ap.parse_args()
    repair = control if args.ref is None else load_reference(args.ref, "control_reference")
    recompute = args.recompute or args.ref is not None
    store = ArtifactStore(args.store)
    robots: dict[str, tuple] = {}
    seqs = touching_seqs = touching = moved = not_clear = invalid = 0
    cpu = 0.0
    worst, worst_deg = "-", 0.0
    for seq, art, fps, rate, exported in _sequences(store, args):
        seqs += 1
        robot_cfg = art.info["config"]["robot"]
        if robot_cfg not in robots:
            robot = load_robot(type(Config().robot).model_validate_json(robot_cfg))
            robots[robot_cfg] = robot, _Separator(robot)
        robot, sep = robots[robot_cfg]
        q = np.asarray(art.arrays["q"], np.float64)
        q = q[-1] if q.ndim == 3 else q  # refine: (rounds, T, n), the last one chosen
        qc = resample(q, fps, rate)
        qc = np.clip(qc, robot.lower + BOX_MARGIN, robot.upper - BOX_MARGIN)
        qc = clamp_velocity(qc, robot.velocity_limits * (1.0 - VELOCITY_MARGIN), rate)
        if recompute:
            t0 = time.process_time()
            exported, clear = repair.control_trajectory_checked(robot, q, fps, rate)
            cpu += time.process_time() - t0
            not_clear += not clear
        exported = np.asarray(exported, np.float64)
        counts = validation_counts(robot, exported, rate)
        invalid += any(v > 0 for v in counts.values())
        bad = [t for t, x in enumerate(qc) if sep.contacts(x, jacobians=False)]
        n = min(len(qc), len(exported))
        drift = np.degrees(np.abs(exported[:n] - qc[:n]).max(axis=1))
        far = np.flatnonzero(drift > args.moved_deg)
        touching_seqs += bool(bad)
        touching += len(bad)
        moved += bool(len(far))
        if drift.max() > worst_deg:
            worst, worst_deg = seq, float(drift.max())
        print(f"{seq} frames={len(q)} samples={len(exported)} touching={bad} "
              f"max_drift_deg={drift.max():.3f} moved_samples={len(far)}"
              f"{f' moved_span={far[0]}-{far[-1]}' if len(far) else ''} "
              f"violations={sum(counts.values()):.0f}")
    print(f"RESULT seqs={seqs} touching_seqs={touching_seqs} touching_samples={touching} moved_seqs={moved} "
          f"max_drift_deg={worst_deg:.3f} worst={worst} not_clear={not_clear} invalid={invalid} "
          f"repair_cpu_s={cpu:.2f}")


if __name__ == "__main__":
    main()
