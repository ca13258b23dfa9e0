"""The G1 shoulder-roll housing against the torso shell on data no test uses (synthetic seed 7):
frames where MuJoCo finds either housing inside the torso's collision geometry (counted with the
robot's exclusions lifted, so the figure means the same whether or not the YAML counts the pair),
the deepest, and the wrists' location error against the human's (scaled) wrist targets.

    python benchmarks/shoulder_housing.py [--n 2] [--seed 7]
"""

from __future__ import annotations

import argparse

import mujoco
import numpy as np


def housing_depths(robot, q: np.ndarray) -> np.ndarray:
    """(T,) deepest signed distance (m) between torso_link and either shoulder-roll link's
    collision geoms (0 where clear), from MuJoCo with only those geoms colliding."""
    m = robot.model.__copy__()
    bodies = [m.body(n).id for n in ("torso_link", "left_shoulder_roll_link", "right_shoulder_roll_link")]
    geoms = np.flatnonzero(np.isin(m.geom_bodyid, bodies) & np.isin(m.geom_group, robot.spec.collision.geom_groups))
    m.geom_contype[:] = 0
    m.geom_conaffinity[:] = 0
    m.geom_contype[geoms] = 1
    m.geom_conaffinity[geoms] = 1
    m.geom_margin[geoms] = 0.0
    m.exclude_signature[:] = 0
    d = mujoco.MjData(m)
    out = np.zeros(len(q))
    for t, qt in enumerate(q):
        d.qpos[:] = robot.qpos(qt)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        out[t] = min([d.contact.dist[i] for i in range(d.ncon)], default=0.0)
    return np.minimum(out, 0.0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    from embody.body import load_body_model
    from embody.config import load_config
    from embody.retarget import retarget, shape_fit
    from embody.robot import load_robot
    from embody.synth import generate_sequence

    cfg = load_config()
    body, robot = load_body_model(cfg.body), load_robot(cfg.robot)
    fit = shape_fit(robot, body, cfg.ik)
    frames = inside = 0
    deepest, errors = 0.0, []
    for i in range(args.n):
        targets, sol = retarget(generate_sequence(args.seed, i), robot, body, fit, cfg.ik)
        depth = housing_depths(robot, sol.q)
        wrists = robot.link_poses(sol.q, ["left_wrist", "right_wrist"])[0]
        err = np.linalg.norm(wrists - targets.wrist_pos, axis=-1)
        frames += len(depth)
        inside += int((depth < 0).sum())
        deepest = min(deepest, float(depth.min()))
        errors.append(err.ravel())
        print(f"clip {i}: housing inside the torso on {int((depth < 0).sum())}/{len(depth)} frames, "
              f"deepest {abs(1000 * depth.min()):.1f} mm; wrist error mean {1000 * err.mean():.1f} mm "
              f"p95 {1000 * np.percentile(err, 95):.1f} mm", flush=True)
    e = np.concatenate(errors)
    print(f"RESULT n={args.n} housing_frames_pct={100 * inside / frames:.2f} housing_depth_max_mm={abs(1000 * deepest):.1f} "
          f"wrist_err_mean_mm={1000 * e.mean():.2f} wrist_err_p95_mm={1000 * np.percentile(e, 95):.2f}", flush=True)


if __name__ == "__main__":
    main()
