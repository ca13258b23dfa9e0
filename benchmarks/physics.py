"""Physics replay of stored runs' exported trajectories: the physics-valid rule's figures.

For every finished sequence of each `--run` in `--store`, the exported 50 Hz array the metrics
step stored (`q_control`) is replayed with `embody.physics.evaluate` (fixed base and standing,
the robot's gains and effort limits), scored against the same human track as the metrics step
(at the exported samples' source times, `source_time`, where the torque and ZMP limits retimed
the array). Per sequence and over the run: how much the retiming slowed the motion down
(`time_stretch_max`, the largest local slowdown; `duration_ratio`, the exported duration over
the source's).
Runs made before the physics step existed work too (this reads only `metrics` and `collide`).
`seconds_per_seq` is the CPU time of `evaluate` per sequence (`time.process_time`; the human
track is built outside it), after one untimed warm-up call per robot (its replay and collision
models are built once per process, as the run's `warm` builds them), with BLAS and torch held to
one thread as a pipeline worker holds them (`flows.threads`): with their default two threads
the process's CPU time also counts OpenBLAS's second thread, and the step's own thread runs
slower (on 6 sequences, back to back at load 4: 0.40-0.48 CPU-s against 0.36-0.39 pinned).
`thread_seconds_per_seq` is the calling thread's alone (`time.thread_time`, the clock of
`pipeline.py`'s `physics_cpu_s`, which also builds the human track). `load1` is the machine's
load average at the end: on a shared machine CPU seconds grow with it (the same code measured
0.47 CPU-s a sequence at load 3-4 and 0.70 on a busier machine), so compare figures taken back
to back. Without --run: every run in the store.

    python benchmarks/physics.py --store DIR [--run RUN ...] [--limit N]

Also, untimed, per sequence: how close the exported samples bring counted geom pairs (the
kinematic check's pairs, `contacts.collision_model`) and how much the fixed-base replay closes
those gaps (exported distance minus simulated distance, of the pairs within 10 mm in the export): a
simulated self-contact needs a pair whose exported clearance is smaller than the closure.

RESULT physics_valid_pct=… palm_p95_mm=… torque_over_samples=… saturated_step_pct=… sim_contacts=…
zmp_margin_min_mm=… fidelity_loss_pct=… standing_ok_pct=… seconds_per_seq=… thread_seconds_per_seq=… retimed_pct=…
time_stretch_max=… duration_ratio_mean=… duration_ratio_max=…
export_clearance_min_mm=… replay_closure_p99_mm=… replay_closure_max_mm=… load1=…
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

#: Pairs within this distance (m) are measured for the clearance figures.
WITHIN = 0.01


def pair_distances(robot, q: np.ndarray) -> list[dict[tuple[int, int], float]]:
    """Per sample of q (T,n): {(geom1, geom2): distance (m)} of the counted pairs within WITHIN
    (MuJoCo's contact distance, negative inside)."""
    from embody.robot.contacts import counted_contacts
    out = []
    for pairs, dists in counted_contacts(robot, q, WITHIN):
        found: dict[tuple[int, int], float] = {}
        for g, d in zip(pairs.tolist(), dists.tolist()):
            key = (min(g), max(g))
            found[key] = min(found.get(key, WITHIN), d)
        out.append(found)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--run", action="append", default=[])
    ap.add_argument("--limit", type=int, default=0)
    args = ap.parse_args()

    from threadpoolctl import threadpool_limits

    from embody.body import load_body_model
    from embody.device import torch_threads
    from embody.export.runs import load_result
    from embody.metrics.embodiments import human_track
    from embody.metrics.fidelity import resample_track
    from collections import Counter

    from embody.physics import evaluate
    from embody.physics.evaluate import sim_contacts
    from embody.report.reader import open_run, run_config
    from embody.retarget.dynamics_limits import duration_ratio, time_stretch, uniform_time
    from embody.robot import load_robot
    from embody.verdicts import physics_valid

    runs = args.run or sorted(p.parent.name for p in (Path(args.store) / "runs").glob("*/manifest.json"))
    rows, palm, cpu, thread_cpu, closures = [], [], [], [], []
    pairs: Counter = Counter()
    steps = saturated = 0
    for run in runs:
        store, manifest = open_run(args.store, run)
        cfg = run_config(manifest)
        robot, body = load_robot(cfg.robot), load_body_model(cfg.body)
        seqs = [(sid, s) for sid, s in sorted(manifest.sequences.items())
                if s["status"] == "ok" and "metrics" in s["steps"]]
        warmed = False
        for sid, seq in seqs[: args.limit or None]:
            art = store.read("metrics", seq["steps"]["metrics"])
            stored = seq["metrics"]["metrics"]
            q = np.asarray(art.arrays["q_control"], dtype=np.float64)
            rate = float(stored["validation_rate_hz"])
            times = art.arrays.get("source_time")
            times = None if times is None else np.asarray(times, dtype=np.float64)
            human = resample_track(human_track(load_result(store, seq, "collide").motion, body), rate, times)
            st = uniform_time(len(q), rate) if times is None else times
            with threadpool_limits(limits=1, user_api="blas"), torch_threads(1):
                if not warmed:
                    evaluate(robot, q, rate, human, cfg.fidelity)
                    warmed = True
                t0, c0 = time.process_time(), time.thread_time()
                res = evaluate(robot, q, rate, human, cfg.fidelity)
                cpu.append(time.process_time() - t0)
                thread_cpu.append(time.thread_time() - c0)
            m = res.metrics
            final = stored.get("fidelity.final", "ik")
            kin = float(stored.get(f"fidelity.{final}.location_err_mm", np.nan))
            rows.append({"run": run, "id": sid, "valid": physics_valid(m), "kin_loc_mm": kin,
                         "stretch": time_stretch(st, rate), "duration": duration_ratio(st, rate),
                         "sim_loc_mm": float(m.get("fidelity.location_err_mm", np.nan)), **m})
            palm.append(res.arrays["palm_err_mm"])
            kin_d, sim_d = pair_distances(robot, q), pair_distances(robot, res.arrays["q_sim"])
            clear_min = min((d for f in kin_d for d in f.values()), default=WITHIN) * 1000.0
            closure = [(k[g] - s.get(g, WITHIN)) * 1000.0 for k, s in zip(kin_d, sim_d) for g in k]
            closures += closure
            rows[-1]["clear_min_mm"] = clear_min
            pairs.update({(robot.name, *k): v for k, v in sim_contacts(robot, res.arrays["q_sim"])[1].items()})
            steps += m["control_steps"]
            saturated += m["saturated_steps"]
            print(f"{run} {sid}: valid={rows[-1]['valid']} torque_over={m['torque_over_samples']} "
                  f"ratio_max={m['torque_ratio_max']:.2f} sat={m['saturated_step_pct']:.1f}% "
                  f"palm_p95={m.get('palm_err_p95_mm', float('nan')):.1f}mm contacts={m['sim_contact_samples']} "
                  f"zmp_min={m['zmp_margin_min_mm']:.0f}mm (multibody {m['zmp_multibody_margin_min_mm']:.0f}mm, "
                  f"floor yaw {m['floor_yaw_moment_max_nm']:.0f} N·m) standing={m['standing_holds']} "
                  f"(tilt {m['standing_pelvis_tilt_max_deg']:.1f}°, CoM off {m['standing_com_offset_max_mm']:.0f} mm, "
                  f"foot slip {m['standing_foot_slip_max_mm']:.0f} mm, lift {m['standing_foot_lift_max_mm']:.1f} mm) "
                  f"loc {rows[-1]['kin_loc_mm']:.1f}->{rows[-1]['sim_loc_mm']:.1f} mm "
                  f"clearance min {clear_min:.2f} mm, closure max {max(closure, default=0.0):.2f} mm "
                  f"stretch {rows[-1]['stretch']:.2f} duration x{rows[-1]['duration']:.2f} cpu={cpu[-1]:.2f}s",
                  flush=True)
    if not rows:
        raise SystemExit("no finished sequences")
    print("self-contacts in simulation, per body pair (samples with that pair penetrating, the "
          "kinematic check's rule; the exported arrays themselves have none):")
    for (name, a, b), n in pairs.most_common():
        print(f"  {name} {a} / {b}: {n}")
    kin = np.nanmean([r["kin_loc_mm"] for r in rows])
    sim = np.nanmean([r["sim_loc_mm"] for r in rows])
    all_palm = np.concatenate(palm)
    print(f"RESULT physics_valid_pct={100.0 * np.mean([r['valid'] for r in rows]):.1f} "
          f"palm_p95_mm={np.percentile(all_palm, 95):.1f} "
          f"torque_over_samples={sum(r['torque_over_samples'] for r in rows)} "
          f"saturated_step_pct={100.0 * saturated / max(1, steps):.1f} "
          f"sim_contacts={sum(r['sim_contact_samples'] for r in rows)} "
          f"zmp_margin_min_mm={min(r['zmp_margin_min_mm'] for r in rows):.0f} "
          f"fidelity_loss_pct={100.0 * (sim - kin) / kin:.1f} "
          f"standing_ok_pct={100.0 * np.mean([r['standing_holds'] for r in rows]):.1f} "
          f"seconds_per_seq={np.mean(cpu):.2f} thread_seconds_per_seq={np.mean(thread_cpu):.2f} "
          f"export_clearance_min_mm={min(r['clear_min_mm'] for r in rows):.2f} "
          f"replay_closure_p99_mm={np.percentile(closures, 99) if closures else 0.0:.2f} "
          f"replay_closure_max_mm={max(closures, default=0.0):.2f} "
          f"retimed_pct={100.0 * np.mean([r['stretch'] > 1.0 + 1e-9 for r in rows]):.1f} "
          f"time_stretch_max={max(r['stretch'] for r in rows):.2f} "
          f"duration_ratio_mean={np.mean([r['duration'] for r in rows]):.2f} "
          f"duration_ratio_max={max(r['duration'] for r in rows):.2f} load1={os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
