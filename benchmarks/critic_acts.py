"""Does the critic act? Synthetic signing clips (seed 11, not a test's data) retargeted to each
robot, then the geometric critic's refinement loop with the default config.

Per robot it counts sequences the critic rejected at round 0, those of them refined by at least
one re-solve, and those rejected with no round at all (issue 36: H1 palm errors of 21 deg over
`accept_palm_deg` 20 with a yaw under the 8 deg the turn needed: rejected, nothing proposed), and
the mean palm angle and location error against the human (the judge's, `critic.refine`) of the
IK-only round and of the result. Collision mitigation is skipped (not what this measures).

    python benchmarks/critic_acts.py [--n 3] [--seed 11] [--robots unitree_g1_dex3,unitree_h1]

Ends with one `RESULT robot=... ` line per robot.
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=3)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--robots", default="unitree_g1_dex3,unitree_h1")
    args = ap.parse_args()

    import torch

    from embody.body import load_body_model
    from embody.config import load_config
    from embody.config.robot import RobotConfig
    from embody.critic import refine
    from embody.retarget import build_targets, shape_fit, solve
    from embody.robot import load_robot
    from embody.synth.generator import generate_sequence

    torch.set_num_threads(1)
    cfg = load_config()
    body = load_body_model(cfg.body)
    motions = [generate_sequence(args.seed, i) for i in range(args.n)]
    for name in args.robots.split(","):
        robot = load_robot(RobotConfig(name=name))
        fit = shape_fit(robot, body, cfg.ik)
        rows = []
        for i, motion in enumerate(motions):
            targets = build_targets(motion, body, fit, robot, cfg.ik)
            result = refine(motion, body, fit, robot, targets, solve(robot, targets, cfg.ik),
                            cfg.critic, cfg.ik, cfg.render)
            first = result.rounds[0]
            rejected = first.accepted is False
            rows.append({"rejected": rejected, "rounds": len(result.rounds) - 1,
                         "accepted": result.accepted,
                         "palm0": first.metrics["palm_deg"], "palm": result.final.metrics["palm_deg"],
                         "loc0": first.metrics["location_err"], "loc": result.final.metrics["location_err"]})
            prims = [p["name"] for p in (first.action or {}).get("primitives_orientation", [])
                     + (first.action or {}).get("primitives_positions", [])]
            print(f"{name} clip {i}: round 0 {'rejected' if rejected else 'accepted'} {prims}, "
                  f"{len(result.rounds) - 1} re-solves, palm {rows[-1]['palm0']:.1f} -> "
                  f"{rows[-1]['palm']:.1f} deg, location {rows[-1]['loc0']:.3f} -> {rows[-1]['loc']:.3f}",
                  flush=True)
        mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
        rejected = [r for r in rows if r["rejected"]]
        print(f"RESULT robot={name} n={len(rows)} rejected_round0={len(rejected)} "
              f"rejected_refined={sum(r['rounds'] >= 1 for r in rejected)} "
              f"rejected_without_round={sum(r['rounds'] == 0 for r in rejected)} "
              f"accepted_final={sum(r['accepted'] for r in rows)} "
              f"palm_deg_ik={mean('palm0'):.2f} palm_deg_final={mean('palm'):.2f} "
              f"location_err_ik={mean('loc0'):.4f} location_err_final={mean('loc'):.4f}", flush=True)


if __name__ == "__main__":
    main()
