"""Where our IK's wrist error on benchmarks/ik_vs_mink.py's frames comes from: the same 4
sequences and targets, mink's feasible frames (plain mink free of MuJoCo contacts and within the
velocity limits), and our solver under several `ik` settings, each one a
variant that switches one source of error off (smoothness, velocity hinge and clamp, posture,
elbow task, torso task, the iteration cap, the collision term). Per setting: all-frame and
feasible-frame wrist error (mm), jerk, collision frames at the source rate and at 50 Hz, velocity
violations and our CPU seconds (`time.process_time`, one thread), in one process so the CPU figures
share the machine's load. Variants that switch the collision term off are not valid solutions:
they say what the term costs. Ends with one `RESULT` line per setting.

    python benchmarks/ik_wrist_sources.py                         # the breakdown set below
    python benchmarks/ik_wrist_sources.py --set w_smooth=0.01 --set w_jerk=0.001 --name mine
        [--base]                                                  # also the default, first
    python benchmarks/ik_wrist_sources.py --set w_wrist_pos=4 --sweep w_smooth=0.04,0.06
        [--cache /tmp/ik_wrist_sources.pkl]   # targets and mink's frames kept between runs

`--cache` is a pickle of this script's own making, not keyed: delete it when the collide step,
the targets or mink's setup change.
"""

from __future__ import annotations

import argparse
import itertools
import os
import pickle
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import yaml  # noqa: E402

from embody.body import load_body_model  # noqa: E402
from embody.collision import mitigate  # noqa: E402
from embody.config import Config  # noqa: E402
from embody.config.ik import IKConfig  # noqa: E402
from embody.retarget import build_targets, shape_fit, solve  # noqa: E402
from embody.retarget.ik import evaluate  # noqa: E402
from embody.retarget.limits import resample  # noqa: E402
from embody.robot import load_robot  # noqa: E402
from embody.robot.contacts import self_collision_contacts  # noqa: E402
from embody.synth import generate_sequence  # noqa: E402

#: One source of error off per variant (the collision-free ones first).
BREAKDOWN: dict[str, dict[str, object]] = {
    "default": {},
    "no_smooth": {"w_smooth": 0.0},
    "smooth_x0.25": {"w_smooth": 0.005},
    "no_velocity": {"w_velocity": 0.0, "enforce_velocity_limits": False},
    "no_posture": {"w_posture": 0.0, "w_waist_posture": 0.0},
    "no_elbow": {"w_elbow_pos": 0.0},
    "no_torso": {"w_torso_rot": 0.0},
    "converged": {"iterations": 200, "tolerance": 1e-7},
    "no_collision": {"w_collision": 0.0, "contact_repair": False, "w_hand_clearance": 0.0},
}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sequences", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="one setting of ik fields instead of the breakdown set (repeatable)")
    parser.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2,...",
                        help="every combination of these values (repeatable; with --set as the base)")
    parser.add_argument("--name", default="custom")
    parser.add_argument("--base", action="store_true", help="with --set: the default first")
    parser.add_argument("--only", nargs="*", default=None, help="breakdown variants to run")
    parser.add_argument("--cache", default=None, help="keep targets and mink's frames here (pickle)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = Config()
    robot = load_robot(config.robot)
    cache = Path(args.cache) if args.cache else None
    if cache is not None and cache.exists():
        all_targets, feasible = pickle.loads(cache.read_bytes())
    else:
        import sys
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from ik_vs_mink import fixed_base_model, run_mink  # the benchmark's own mink

        body = load_body_model(config.body)
        fit = shape_fit(robot, body, config.ik)
        seqs = [mitigate(generate_sequence(args.seed, i), body, config.collision).motion
                for i in range(args.sequences)]
        all_targets = [build_targets(m, body, fit, robot) for m in seqs]
        model = fixed_base_model(robot)
        feasible = []
        for targets in all_targets:
            theirs = run_mink(robot, model, targets)
            frames, _ = evaluate(robot, theirs, targets)
            ok = np.ones(len(theirs), dtype=bool)
            ok[1:] = (np.abs(np.diff(theirs, axis=0)) * targets.fps
                      <= robot.velocity_limits * (1 + 1e-9)).all(1)
            feasible.append((frames["self_contacts"] == 0) & ok)
        if cache is not None:
            cache.write_bytes(pickle.dumps((all_targets, feasible)))
    if args.set or args.sweep:
        custom = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
        settings = {"default": {}} if args.base else {}
        axes = [(k, [yaml.safe_load(x) for x in v.split(",")]) for k, v in (kv.split("=", 1) for kv in args.sweep)]
        for values in itertools.product(*[v for _, v in axes]):
            over = dict(zip([k for k, _ in axes], values))
            name = ",".join(f"{k}={v}" for k, v in over.items()) or args.name
            settings[name] = custom | over
    else:
        settings = {k: v for k, v in BREAKDOWN.items() if args.only is None or k in args.only}
    solve(robot, all_targets[0], IKConfig(iterations=1))  # warm-up (proxies, caches, chains)
    print("feasible frames per sequence:", [int(f.sum()) for f in feasible], "of",
          [len(f) for f in feasible])
    for name, over in settings.items():
        cfg = IKConfig.model_validate({**config.ik.model_dump(), **over})
        cpu, jerk, coll, coll50, viol, rot = 0.0, [], 0, 0, 0.0, []
        err_all, err_feas, per_seq = [], [], []
        for targets, feas in zip(all_targets, feasible):
            c0 = time.process_time()
            sol = solve(robot, targets, cfg)
            cpu += time.process_time() - c0
            wrist = sol.frame_metrics["wrist_pos_err_mm"].mean(1)
            err_all.append(wrist)
            err_feas.append(wrist[feas])
            jerk.append(sol.metrics["jerk"])
            rot.append(sol.metrics["wrist_rot_err_deg"])
            coll += int(sol.metrics["self_collision_frames"])
            coll50 += int((self_collision_contacts(robot, resample(sol.q, targets.fps, cfg.control_rate_hz)) > 0).sum())
            viol += sol.metrics["velocity_violations"]
            per_seq.append(f"{wrist.mean():.2f}/{wrist[feas].mean():.2f}/{sol.metrics['jerk']:.0f}")
        frames = sum(len(e) for e in err_all)
        print(f"{name:>14}: per seq all/feasible mm/jerk " + " ".join(per_seq))
        print(f"RESULT setting={name} wrist_mm={np.mean([e.mean() for e in err_all]):.2f} "
              f"feasible_wrist_mm={np.concatenate(err_feas).mean():.2f} rot_deg={np.mean(rot):.2f} jerk={np.mean(jerk):.1f} "
              f"collision_frames={coll} collision_frames_50hz={coll50} vel_viol={viol / len(jerk):.1f} "
              f"cpu_s={cpu:.2f} cpu_fps={frames / cpu:.1f}", flush=True)


if __name__ == "__main__":
    main()
