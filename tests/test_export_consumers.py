"""Exported files loaded by their consumers' own logic, replayed here step by step.

* BeyondMimic (HybridRobotics/whole_body_tracking `scripts/csv_to_npz.py`): `np.loadtxt(file,
  delimiter=",")` → float32; base position `[:, :3]`, base quaternion `[:, 3:7]` reordered
  `[3, 0, 1, 2]` (xyzw → wxyz), joints `[:, 7:]` assigned to the 29 G1 joints it names
  (`joint_pos[:, robot.find_joints(names, preserve_order=True)[0]] = motion_dof_pos`). IsaacLab's
  articulation orders joints its own way, so the replay uses a different order than the MJCF.
* GMR (YanjieZe/GMR `general_motion_retargeting.utils` `load_robot_motion`): `pickle.load`;
  `fps`, `root_pos`, `root_rot[:, [3, 0, 1, 2]]`, `dof_pos`, `local_body_pos`, `link_body_list`
  read by key; MuJoCo qpos = root_pos | root_rot | dof_pos.

The truth is the robot pose of the trajectory itself: every body's world position from plain
MuJoCo forward kinematics of the qpos each consumer builds, against the qpos of `q`.
"""

from __future__ import annotations

import pickle

import mujoco
import numpy as np
import pandas as pd
import pytest
import torch

from embody.export.library import Trajectory, check_library, export_library
from embody.robot import load_robot

#: BeyondMimic's `joint_names` list in `scripts/csv_to_npz.py`, copied from its source.
BEYONDMIMIC_NAMES = [
    "left_hip_pitch_joint", "left_hip_roll_joint", "left_hip_yaw_joint", "left_knee_joint",
    "left_ankle_pitch_joint", "left_ankle_roll_joint", "right_hip_pitch_joint",
    "right_hip_roll_joint", "right_hip_yaw_joint", "right_knee_joint", "right_ankle_pitch_joint",
    "right_ankle_roll_joint", "waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint",
    "left_shoulder_pitch_joint", "left_shoulder_roll_joint", "left_shoulder_yaw_joint",
    "left_elbow_joint", "left_wrist_roll_joint", "left_wrist_pitch_joint", "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint", "right_shoulder_roll_joint", "right_shoulder_yaw_joint",
    "right_elbow_joint", "right_wrist_roll_joint", "right_wrist_pitch_joint",
    "right_wrist_yaw_joint"]


@pytest.fixture(scope="module")
def robot():
    return load_robot()


@pytest.fixture(scope="module")
def trajectory(robot) -> Trajectory:
    """Six frames with every joint, fingers included, away from zero and moving."""
    lo, hi = robot.lower, robot.upper
    mid = np.where(np.isfinite(lo) & np.isfinite(hi), (lo + hi) / 2, 0.0)
    span = np.where(np.isfinite(lo) & np.isfinite(hi), (hi - lo) / 2, 0.5)
    phase = np.linspace(0, 1, 6)[:, None] * np.linspace(0.3, 1.3, robot.n_joints)[None]
    q = mid + 0.6 * span * np.sin(2 * np.pi * phase)
    return Trajectory(id="wave", robot=robot.name, joint_names=tuple(robot.joint_names), q=q, dt=0.02)


def _body_positions(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(model)
    out = []
    for row in qpos:
        data.qpos[:] = row
        mujoco.mj_kinematics(model, data)
        out.append(data.xpos.copy())
    return np.stack(out)


def _truth(robot, q: np.ndarray) -> np.ndarray:
    return _body_positions(robot.model, np.stack([robot.qpos(row) for row in q]))


def test_beyondmimic_csv_as_csv_to_npz_loads_it(robot, trajectory, tmp_path) -> None:
    path = trajectory.save(tmp_path / "wave", "beyondmimic", robot)
    motion = torch.from_numpy(np.loadtxt(path, delimiter=",")).to(torch.float32)
    base_pos = motion[:, :3]
    base_rot = motion[:, 3:7][:, [3, 0, 1, 2]]
    motion_dof_pos = motion[:, 7:]

    # IsaacLab's articulation joint order is not the MJCF's: index by name as find_joints does.
    articulation = sorted(robot.joint_names)
    robot_joint_indexes = [articulation.index(n) for n in BEYONDMIMIC_NAMES]
    joint_pos = torch.zeros(len(motion), len(articulation))
    joint_pos[:, robot_joint_indexes] = motion_dof_pos  # raises unless exactly 29 columns

    # The fingers BeyondMimic does not drive come from the documented side file, by name.
    side = pd.read_csv(tmp_path / "wave.extra_joints.csv")
    assert sorted(side.columns) == sorted(set(robot.joint_names) - set(BEYONDMIMIC_NAMES))
    assert len(side.columns) == 14 and len(side) == len(motion)
    joint_pos[:, [articulation.index(n) for n in side.columns]] = torch.from_numpy(
        side.to_numpy(np.float32))

    by_name = dict(zip(articulation, joint_pos.T.numpy().astype(np.float64)))
    q = np.stack([by_name[n] for n in robot.joint_names], axis=1)
    qpos = np.stack([robot.qpos(row) for row in q])
    qpos[:, :3], qpos[:, 3:7] = base_pos.numpy(), base_rot.numpy()
    np.testing.assert_allclose(base_rot.numpy(), np.tile(robot.model.qpos0[3:7], (len(q), 1)),
                               atol=1e-6)  # the MJCF's own root, unit quaternion, wxyz
    err_mm = 1000 * np.abs(_body_positions(robot.model, qpos) - _truth(robot, trajectory.q)).max()
    assert err_mm < 0.01, err_mm  # float32 rounding only


def test_beyondmimic_library_round_trip(robot, trajectory, tmp_path) -> None:
    """The export re-validates the csv with its side file, lists it, and a re-export of
    another format removes both."""
    from embody.retarget.validation import validation_counts

    base = robot.rest.copy()  # forearms forward, one hand above the other
    for name, v in (("left_shoulder_pitch_joint", -0.4), ("right_shoulder_pitch_joint", -0.8),
                    ("left_elbow_joint", 1.0), ("right_elbow_joint", 1.0),
                    ("left_shoulder_yaw_joint", -0.5), ("right_shoulder_yaw_joint", 0.5)):
        base[robot.joint_index(name)] = v
    # tiny: physics-valid too (the fixture's 6-frame wave asks for more torque at larger amplitudes)
    q = robot.clip(base + 0.0005 * (trajectory.q - trajectory.q.mean(axis=0)))
    counts = validation_counts(robot, q, 50.0)
    assert not any(counts.values()), counts
    gentle = Trajectory(id="wave", robot=robot.name, joint_names=trajectory.joint_names, q=q,
                        dt=0.02, validation=counts)
    export_library([gentle], tmp_path, "beyondmimic", robot=robot)
    assert (tmp_path / "wave.csv").is_file() and (tmp_path / "wave.extra_joints.csv").is_file()
    table = check_library(tmp_path, robot)
    assert table["ok"].tolist() == [True], str(table.to_dict("records"))
    import json
    assert json.loads((tmp_path / "library.json").read_text())["sequences"][0][
        "companion_files"] == ["wave.extra_joints.csv"]
    export_library([gentle], tmp_path, "npz", robot=robot)
    assert not (tmp_path / "wave.csv").exists() and not (tmp_path / "wave.extra_joints.csv").exists()


def test_gmr_pickle_as_load_robot_motion_loads_it(robot, trajectory, tmp_path) -> None:
    path = trajectory.save(tmp_path / "wave", "gmr", robot)
    with open(path, "rb") as f:
        motion_data = pickle.load(f)
        motion_fps = motion_data["fps"]
        motion_root_pos = motion_data["root_pos"]
        motion_root_rot = motion_data["root_rot"][:, [3, 0, 1, 2]]  # xyzw -> wxyz
        motion_dof_pos = motion_data["dof_pos"]
        motion_data["local_body_pos"], motion_data["link_body_list"]  # read by key: must exist
    assert motion_fps == 50
    qpos = np.concatenate([motion_root_pos, motion_root_rot, motion_dof_pos], axis=1)
    assert qpos.shape == (len(trajectory.q), robot.model.nq)
    err_mm = 1000 * np.abs(_body_positions(robot.model, qpos) - _truth(robot, trajectory.q)).max()
    assert err_mm < 1e-6, err_mm
