"""The trajectory library writer: valid trajectories exported, failing ones excluded and listed."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from embody.errors import InputError
from embody.export.library import Trajectory, export_library
from embody.robot import load_robot

ROBOT = load_robot()
NAMES = tuple(ROBOT.joint_names)
ELBOWS = [ROBOT.joint_index(n) for n in ("left_elbow_joint", "right_elbow_joint")]


def _traj(sid: str, **validation) -> Trajectory:
    q = np.tile(ROBOT.rest, (30, 1))
    q[:, ELBOWS] = np.linspace(0, 1, 30)[:, None] * np.array([0.2, 0.3])  # forearms rise, apart
    return Trajectory(id=sid, robot="unitree_g1_dex3", joint_names=NAMES, q=q, dt=0.02,
                      text=f"sign {sid}", validation={"joint_limit_violations": 0,
                      "velocity_violations": 0, "self_collision_frames": 0,
                      "torque_viol": 0, "wrist_pos_mean_mm": 12.5, **validation})


@pytest.mark.parametrize("fmt", ["npz", "csv"])
def test_export_excludes_failing(tmp_path, fmt) -> None:
    trajs = [_traj("a"), _traj("b/2", self_collision_frames=3), _traj("c", joint_limit_violations=1)]
    library, excluded = export_library(trajs, tmp_path, fmt)
    assert library["id"].tolist() == ["a"]
    assert excluded["id"].tolist() == ["b/2", "c"]
    assert excluded["reason"].tolist() == ["self_collision_frames=3", "joint_limit_violations=1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["library.csv", "library.json",
                                                                 "excluded.csv", f"a.{fmt}"])
    index = pd.read_csv(tmp_path / "library.csv")
    assert index.loc[0, "file"] == f"a.{fmt}" and index.loc[0, "frames"] == 30
    assert index.loc[0, "validation.wrist_pos_mean_mm"] == 12.5
    assert index.loc[0, "written.self_collision_frames"] == 0
    if fmt == "npz":
        back = Trajectory.load(tmp_path / "a.npz")
        np.testing.assert_array_equal(back.q, trajs[0].q)
        assert back.joint_names == NAMES and back.dt == 0.02 and back.text == "sign a"
        assert back.validation == trajs[0].validation and back.id == "a"
        again = trajs[0].save_npz(tmp_path / "again.npz")
        assert again.read_bytes() == (tmp_path / "a.npz").read_bytes()
    else:
        table = pd.read_csv(tmp_path / "a.csv")
        assert table.columns.tolist() == ["time", *NAMES]
        np.testing.assert_allclose(table["time"], np.arange(30) * 0.02, atol=1e-12)
        np.testing.assert_array_equal(table[list(NAMES)].to_numpy(), trajs[0].q)  # %.17g: exact


def test_reexport_removes_stale_files(tmp_path) -> None:
    export_library([_traj("a"), _traj("b")], tmp_path)
    (tmp_path / "mine.txt").write_text("keep")
    export_library([_traj("a"), _traj("b", velocity_violations=2)], tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "a.npz", "excluded.csv", "library.csv", "library.json", "mine.txt"]


def test_safe_names_stay_distinct() -> None:
    from embody.export.library import safe_name

    assert safe_name("seq_001") == "seq_001"
    assert safe_name("a/b") != safe_name("a_b") and safe_name("a/b").startswith("a_b-")


def test_bad_inputs(tmp_path) -> None:
    with pytest.raises(InputError, match="q"):
        Trajectory(id="x", robot="r", joint_names=NAMES, q=np.zeros((5, 2)), dt=0.02)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz"):
        Trajectory.load(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="npz"):
        Trajectory.load(tmp_path / "a.csv")


def test_npz_carries_the_samples_source_times(tmp_path) -> None:
    """A retimed trajectory (slowed down three times over its middle) keeps each sample's time on
    the source's timeline in its npz, read back as written; one without them has none."""
    slow = np.r_[np.arange(10) * 0.02, 0.2 + np.arange(1, 11) * 0.02 / 3, 0.2 + 0.2 / 3 + np.arange(1, 11) * 0.02]
    traj = _traj("a")
    timed = Trajectory(id="t", robot=traj.robot, joint_names=NAMES, q=traj.q, dt=0.02, source_time=slow[:30])
    back = Trajectory.load(timed.save(tmp_path / "t", "npz"))
    np.testing.assert_array_equal(back.source_time, slow[:30])
    assert Trajectory.load(traj.save(tmp_path / "a", "npz")).source_time is None
