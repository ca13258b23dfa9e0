"""Exported files replayed through their consumers' own loading logic, on a synthetic clip the
tests do not use (seed 31): BeyondMimic's `scripts/csv_to_npz.py` (loadtxt, float32, root
`[:, :3]`, quaternion `[:, 3:7][:, [3, 0, 1, 2]]`, `joint_pos[:, find_joints(names)] =
motion[:, 7:]`) and GMR's `load_robot_motion` (pickle; `root_rot[:, [3, 0, 1, 2]]`; qpos =
root_pos | root_rot | dof_pos). Plain MuJoCo FK of each consumer's qpos against that of the
trajectory: the largest body-position error (mm) over every body and sample, or the error the
consumer's load raises. The fingers BeyondMimic does not drive come from the side file by name.

    python benchmarks/export_consumers.py [--seed 31]
"""

from __future__ import annotations

import argparse
import pickle
import tempfile
from pathlib import Path

import mujoco
import numpy as np
import pandas as pd

# The sibling benchmark holds the one copy of BeyondMimic's joint list.
from export_check import BEYONDMIMIC_G1_JOINTS as BM


def _xpos(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    data, out = mujoco.MjData(model), []
    for row in qpos:
        data.qpos[:] = row
        mujoco.mj_kinematics(model, data)
        out.append(data.xpos.copy())
    return np.stack(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=31)
    args = ap.parse_args()
    import torch

    from embody.body import load_body_model
    from embody.config import load_config
    from embody.export.library import Trajectory
    from embody.retarget import build_targets, shape_fit, solve
    from embody.retarget.control import control_trajectory
    from embody.robot import load_robot
    from embody.synth.generator import generate_sequence

    torch.set_num_threads(1)
    cfg = load_config()
    robot, body = load_robot(cfg.robot), load_body_model(cfg.body)
    motion = generate_sequence(args.seed, 0)
    targets = build_targets(motion, body, shape_fit(robot, body, cfg.ik), robot, cfg.ik)
    q = control_trajectory(robot, solve(robot, targets, cfg.ik).q, motion.fps, 50.0)
    traj = Trajectory("clip", robot.name, tuple(robot.joint_names), q, 0.02)
    truth = _xpos(robot.model, np.stack([robot.qpos(r) for r in q]))
    with tempfile.TemporaryDirectory() as tmp:
        path = traj.save(Path(tmp) / "clip", "beyondmimic", robot)
        motion_bm = np.loadtxt(path, delimiter=",").astype(np.float32)
        names = sorted(robot.joint_names)  # an articulation order other than the MJCF's
        joint_pos = np.zeros((len(q), len(names)), np.float32)
        try:
            joint_pos[:, [names.index(n) for n in BM]] = motion_bm[:, 7:]
            side = Path(tmp) / "clip.extra_joints.csv"
            if side.is_file():
                extra = pd.read_csv(side)
                joint_pos[:, [names.index(n) for n in extra.columns]] = extra.to_numpy(np.float32)
            by_name = dict(zip(names, joint_pos.T.astype(np.float64)))
            qpos = np.stack([robot.qpos(r) for r in np.stack([by_name[n] for n in robot.joint_names], 1)])
            qpos[:, :3], qpos[:, 3:7] = motion_bm[:, :3], motion_bm[:, 3:7][:, [3, 0, 1, 2]]
            bm = f"{1000 * np.abs(_xpos(robot.model, qpos) - truth).max():.4f}"
        except ValueError as exc:
            bm = f"fails({str(exc).split(':')[0].replace(' ', '_')})"
        with open(traj.save(Path(tmp) / "clip", "gmr", robot), "rb") as f:
            gmr = pickle.load(f)
        qpos = np.concatenate([gmr["root_pos"], gmr["root_rot"][:, [3, 0, 1, 2]], gmr["dof_pos"]], 1)
        _ = gmr["local_body_pos"], gmr["link_body_list"]
        gmr_err = 1000 * np.abs(_xpos(robot.model, qpos) - truth).max()
    print(f"RESULT samples={len(q)} bodies={robot.model.nbody} csv_joint_columns={motion_bm.shape[1] - 7} "
          f"beyondmimic_max_body_err_mm={bm} gmr_max_body_err_mm={gmr_err:.4f}")


if __name__ == "__main__":
    main()
