"""Torque and balance feasibility of the exported 50 Hz trajectories, before and after the
control-rate dynamics limits (`embody.retarget.dynamics_limits`, `ik.dynamics_limits`).

Per default synthetic sequence (seed 0; collision mitigation read from fidelity.py's cache):
location-preserving targets, the IK solved with the dynamics limits off; its exported control-rate
array is "before". "After" is the same source-rate solution through the control stage with the
limits on (`control_trajectory(..., limits=...)`): exactly what the retarget step exports, since
the limits act only on the control-rate array. Each array is measured against the truth, not the
pipeline's own targets:

- torque: `embody.robot.dynamics.inverse_dynamics` (MuJoCo `mj_inverse`, fixed base, free
  motion, along the natural cubic spline through the control-rate samples that the export
  commands, plus the joints' dry friction) against the MJCF effort limits: samples (sample,
  joint) over the limit, sequences with any, the worst |tau|/limit;
- replay: the exported commands (`physics.commands`) played in MuJoCo with the pelvis welded at
  the robot's gains (`physics.replay_fixed`): sequences with a saturated motor, the share of
  saturated control steps, palm tracking p95 (mm);
- balance: `dynamics.zmp` (cart-table ZMP, legs at the `stand` keyframe): the smallest margin
  inside the feet polygon (mm; negative: outside), sequences below `ik.zmp_margin`;
- validity: MuJoCo self-collision samples, joint-limit and velocity violations (`validation_counts`);
- sign fidelity on the exported array against the human resampled to the control rate, as the
  metrics step scores it (`compare_with`): location error (body scales), location agreement within
  10 cm of a face/chest landmark (%), hand-hand contact F1 on the contact signs, palm angle (deg),
  handshape error, robot penetration frames.

    python benchmarks/torque_feasibility.py [--n 24] [--save DIR | --load DIR]

`--save DIR` keeps each solve (source-rate q, fps) so `--load DIR` re-measures without solving.
Ends with `RESULT sequences=… before_over=… before_seqs=… before_worst=… before_zmp_min_mm=…
after_over=… after_seqs=… after_worst=… after_zmp_min_mm=… after_zmp_short_seqs=… after_contacts=…
after_velocity=… after_limits=… location_err_before=… location_err_after=… agree10_before=…
agree10_after=… contact_f1_before=… contact_f1_after=… palm_before=… palm_after=…
handshape_before=… handshape_after=… penetration_before=… penetration_after=… limits_s_per_seq=…`
(over: (sample, joint) pairs over the effort limit itself; seqs: sequences with any; worst: the
largest |tau|/limit; zmp_short_seqs: sequences whose ZMP comes closer than `ik.zmp_margin` to
the feet's edge; limits_s_per_seq: the control stage with the limits, per sequence).

Measured 2026-11-29 on one input set for both codes (`--load`: each sequence's final source-rate
solve from a stored default run, "before" its kinematic 50 Hz array; machine at load 11-20, so
the seconds are inflated). Previous solve (central-difference torque, Gauss-Newton from the input;
its `over` counted with central differences): `RESULT sequences=24 before_over=1609 before_seqs=24
before_worst=7.83 before_zmp_min_mm=-1317.3 after_over=167 after_seqs=6 after_worst=3.22
after_zmp_min_mm=-212.6 after_zmp_short_seqs=15 after_contacts=0 after_velocity=0 after_limits=0
location_err_before=0.096 location_err_after=0.117 agree10_before=94.729 agree10_after=92.558
contact_f1_before=0.967 contact_f1_after=0.927 palm_before=4.797 palm_after=5.287
handshape_before=0.097 handshape_after=0.097 penetration_before=0.000 penetration_after=0.000
limits_s_per_seq=62.55`. This solve (spline torque with friction and lag, low-passed start):
`RESULT sequences=24 before_over=4307 before_seqs=24 before_worst=13.92 before_zmp_min_mm=-1317.3
after_over=577 after_seqs=4 after_worst=11.98 after_zmp_min_mm=-685.8 before_sat_seqs=24
before_sat_pct=17.31 before_palm_p95_max=88.4 after_sat_seqs=4 after_sat_pct=1.98
after_palm_p95_max=83.1 after_export_valid=20 after_zmp_short_seqs=4 after_contacts=0
after_velocity=0 after_limits=0 location_err_before=0.096 location_err_after=0.114
agree10_before=94.729 agree10_after=94.574 contact_f1_before=0.967 contact_f1_after=0.885
palm_before=4.797 palm_after=4.777 handshape_before=0.097 handshape_after=0.098
penetration_before=0.000 penetration_after=0.000 limits_s_per_seq=21.82` (20 sequences feasible:
0 saturated steps, palm p95 0.7-1.1 mm; seqs 0, 6, 15, 17 not: their low-pass makes contacts
that no push clears).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fidelity import _setup, agree10, mitigated, sign_f1, target_counts  # noqa: E402

from embody.metrics.embodiments import human_track, scored_robot_track  # noqa: E402
from embody.metrics.fidelity import LOCATION_LANDMARKS, compare_with, resample_track  # noqa: E402
from embody.physics import commands, replay_fixed  # noqa: E402
from embody.retarget import build_targets, solve  # noqa: E402
from embody.retarget.control import control_trajectory  # noqa: E402
from embody.retarget.dynamics_limits import DynamicsLimits  # noqa: E402
from embody.retarget.validation import validation_counts  # noqa: E402
from embody.robot.dynamics import effort_limits, inverse_dynamics, zmp  # noqa: E402
from embody.synth.generator import generate_sequence  # noqa: E402


def dynamics_figures(robot, q: np.ndarray, rate: float) -> dict[str, float]:
    """Samples over the effort limit, the worst ratio and the smallest ZMP margin (mm) of q."""
    ratio = np.abs(inverse_dynamics(robot, q, 1.0 / rate)) / effort_limits(robot)
    _, _, margin = zmp(robot, q, 1.0 / rate)
    worst = np.unravel_index(np.argmax(ratio), ratio.shape)
    return {"over": float((ratio > 1.0).sum()), "worst": float(ratio.max()),
            "worst_joint": robot.joint_names[worst[1]], "zmp_min_mm": float(margin.min() * 1000.0)}


def replay_figures(robot, q: np.ndarray, rate: float) -> dict[str, float]:
    """The exported commands replayed with the pelvis welded: saturated steps (%) and palm p95 (mm)."""
    fixed = replay_fixed(robot, commands(robot, q, rate))
    r = fixed.rollout
    sat = (np.abs(r.demand) >= r.limit * (1.0 - 1e-9)).any(1)
    names = [n for n in robot.spec.landmarks if n.endswith("_palm")]
    ref, _, _ = robot.landmark_points(q, names)
    sim, _, _ = robot.landmark_points(fixed.q50, names)
    err = np.linalg.norm(sim - ref, axis=-1) * 1000.0
    return {"sat_pct": 100.0 * float(sat.mean()), "palm_p95": float(np.percentile(err, 95))}


def fidelity_figures(robot, q: np.ndarray, rate: float, human, motion, cfg) -> dict[str, float]:
    track = scored_robot_track(robot, q, rate, human, cfg.fidelity)
    frames, m = compare_with(human, track, cfg.fidelity)
    frames["location_names"] = [n for n in LOCATION_LANDMARKS if human.has(n) and track.has(n)]
    m.update(target_counts(frames, human, motion, rate))
    return m


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=24, help="default synthetic sequences (seed 0)")
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--save", type=Path, default=None, help="keep each solve here")
    ap.add_argument("--load", type=Path, default=None, help="read the solves kept by --save")
    ap.add_argument("--cache", type=Path, default=Path(".cache/fidelity-collide"))
    args = ap.parse_args()
    ctx = _setup(1)
    cfg, body, robot, fit = ctx["cfg"], ctx["body"], ctx["robot"], ctx["fit"]
    off = cfg.ik.model_copy(update={"dynamics_limits": False})
    limits = DynamicsLimits.from_config(cfg.ik)
    rate = cfg.ik.control_rate_hz
    rows: dict[str, list[dict]] = {"before": [], "after": []}
    contacts_after, seconds = 0.0, []
    for i in range(args.first, args.first + args.n):
        motion = mitigated(generate_sequence(0, i), cfg, body, args.cache)
        path = None if args.load is None else args.load / f"seq_{i:03d}.npz"
        if path is not None and path.exists():
            with np.load(path) as z:
                q, fps, before = z["q"], float(z["fps"]), z["q_control"]
        else:
            sol = solve(robot, build_targets(motion, body, fit, robot, cfg.ik), off)
            q, fps, before = sol.q, sol.fps, sol.q_control
            if args.save is not None:
                args.save.mkdir(parents=True, exist_ok=True)
                np.savez(args.save / f"seq_{i:03d}.npz", q=q, fps=fps, q_control=before)
        t0 = time.perf_counter()
        after = control_trajectory(robot, q, fps, rate, off.contact_repair, limits=limits)
        seconds.append(time.perf_counter() - t0)
        human = resample_track(human_track(motion, body), rate)
        line = [f"seq{i:02d}"]
        for name, arr in (("before", before), ("after", after)):
            row = dynamics_figures(robot, arr, rate)
            row.update(validation_counts(robot, arr, rate))
            row.update(replay_figures(robot, arr, rate))
            row.update(fidelity_figures(robot, arr, rate, human, motion, cfg))
            rows[name].append(row)
            line.append(f"{name}: over={row['over']:.0f} worst={row['worst']:.2f}({row['worst_joint']}) "
                        f"zmp={row['zmp_min_mm']:.0f}mm coll={row['self_collision_frames']:.0f} "
                        f"vel={row['velocity_violations']:.0f} sat={row['sat_pct']:.2f}% palm95={row['palm_p95']:.1f}mm "
                        f"loc={row['location_err']:.3f}")
        contacts_after += rows["after"][-1]["self_collision_frames"]
        change = np.degrees(np.abs(after - before).max()) if after.shape == before.shape else float("nan")
        print("  ".join(line) + f"  max_change={change:.1f}deg t={seconds[-1]:.1f}s", flush=True)

    def total(name: str, key: str) -> float:
        return float(sum(r[key] for r in rows[name]))

    def mean(name: str, key: str) -> float:
        return float(np.nanmean([r[key] for r in rows[name]]))

    out = {"sequences": len(seconds)}
    for name in ("before", "after"):
        out[f"{name}_over"] = f"{total(name, 'over'):.0f}"
        out[f"{name}_seqs"] = f"{sum(r['over'] > 0 for r in rows[name])}"
        out[f"{name}_worst"] = f"{max(r['worst'] for r in rows[name]):.2f}"
        out[f"{name}_zmp_min_mm"] = f"{min(r['zmp_min_mm'] for r in rows[name]):.1f}"
    for name in ("before", "after"):
        out[f"{name}_sat_seqs"] = f"{sum(r['sat_pct'] > 0 for r in rows[name])}"
        out[f"{name}_sat_pct"] = f"{mean(name, 'sat_pct'):.2f}"
        out[f"{name}_palm_p95_max"] = f"{max(r['palm_p95'] for r in rows[name]):.1f}"
    out["after_export_valid"] = f"{sum(r['over'] == 0 and r['self_collision_frames'] == 0 and r['velocity_violations'] == 0 and r['joint_limit_violations'] == 0 for r in rows['after'])}"
    out["after_zmp_short_seqs"] = f"{sum(r['zmp_min_mm'] < 1000 * limits.zmp_margin - 0.5 for r in rows['after'])}"
    out["after_contacts"] = f"{contacts_after:.0f}"
    out["after_velocity"] = f"{total('after', 'velocity_violations'):.0f}"
    out["after_limits"] = f"{total('after', 'joint_limit_violations'):.0f}"
    for key, fn in (("location_err", lambda n: mean(n, "location_err")),
                    ("agree10", lambda n: agree10(rows[n], "")),
                    ("contact_f1", lambda n: sign_f1(rows[n], "")),
                    ("palm", lambda n: mean(n, "palm_deg")),
                    ("handshape", lambda n: mean(n, "handshape_err")),
                    ("penetration", lambda n: total(n, "penetration_frames"))):
        for name in ("before", "after"):
            out[f"{key}_{name}"] = f"{fn(name):.3f}"
    out["limits_s_per_seq"] = f"{np.mean(seconds):.2f}"
    print("RESULT " + " ".join(f"{k}={v}" for k, v in out.items()))


if __name__ == "__main__":
    main()
