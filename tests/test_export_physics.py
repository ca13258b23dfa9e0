"""The exported npz's low-level command fields, and `embody export --check`'s physics rule."""

from __future__ import annotations

import io
import zipfile

import numpy as np

from embody.cli import main
from embody.export.library import Trajectory, check_library, export_library
from embody.physics import actuation
from embody.robot import load_robot
from embody.robot.dynamics import effort_limits, inverse_dynamics

ROBOT = load_robot()
NAMES = tuple(ROBOT.joint_names)


def _traj(sid: str) -> Trajectory:
    q = np.tile(ROBOT.rest, (40, 1))
    elbows = [ROBOT.joint_index(n) for n in ("left_elbow_joint", "right_elbow_joint")]
    q[:, elbows] = (0.5 - 0.5 * np.cos(np.linspace(0, np.pi, 40)))[:, None] * np.array([0.2, 0.3])
    return Trajectory(id=sid, robot="unitree_g1_dex3", joint_names=NAMES, q=q, dt=0.02,
                      validation={"joint_limit_violations": 0, "velocity_violations": 0,
                                  "self_collision_frames": 0, "torque_viol": 0})


def _rewrite(path, **arrays) -> None:
    """Replace arrays in an npz in place (a tampered or hand-made file)."""
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    data.update(arrays)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in data.items():
            arr = io.BytesIO()
            np.lib.format.write_array(arr, np.asarray(v), allow_pickle=False)
            zf.writestr(f"{k}.npy", arr.getvalue())
    path.write_bytes(buf.getvalue())


def test_npz_carries_the_low_level_command_fields(tmp_path) -> None:
    traj = _traj("a")
    library, _ = export_library([traj], tmp_path, "npz", robot=ROBOT)
    with np.load(tmp_path / "a.npz", allow_pickle=False) as z:
        assert {"q", "qd", "tau_ff", "kp", "kd", "control_rate_hz"} <= set(z.files)
        q, qd, tau, kp, kd = (z[k] for k in ("q", "qd", "tau_ff", "kp", "kd"))
        rate = float(z["control_rate_hz"])
    assert qd.shape == q.shape == tau.shape == (40, len(NAMES)) and kp.shape == kd.shape == (len(NAMES),)
    # q̇: the slope of the natural cubic spline through q, the curve a (q, q̇) player interpolates
    from scipy.interpolate import CubicSpline
    spline = CubicSpline(np.arange(40) * 0.02, q, axis=0, bc_type="natural")
    np.testing.assert_allclose(qd, spline(np.arange(40) * 0.02, 1), atol=1e-9)
    np.testing.assert_allclose(tau, inverse_dynamics(ROBOT, q, 0.02), atol=1e-9)
    act = actuation(ROBOT)
    np.testing.assert_array_equal(kp, act.kp)
    assert kp[ROBOT.joint_index("left_elbow_joint")] == 80.0 and kd[ROBOT.joint_index("left_wrist_pitch_joint")] == 1.5
    assert kp[ROBOT.joint_index("right_hand_index_0_joint")] == 1.5 and rate == 250.0
    # holding the arms against gravity takes torque at the shoulders, far below their 25 N·m
    shoulder = ROBOT.joint_index("left_shoulder_pitch_joint")
    assert 0.1 < np.abs(tau[:, shoulder]).max() < 25.0


def test_check_fails_a_file_whose_torques_exceed_the_limits(tmp_path) -> None:
    export_library([_traj("a"), _traj("b")], tmp_path, "npz", robot=ROBOT)
    with np.load(tmp_path / "b.npz", allow_pickle=False) as z:
        tau = z["tau_ff"].copy()
    wrist = ROBOT.joint_index("right_wrist_pitch_joint")
    tau[10:13, wrist] = 1.5 * effort_limits(ROBOT)[wrist]  # three samples ask for 1.5× the limit
    _rewrite(tmp_path / "b.npz", tau_ff=tau)
    table = check_library(tmp_path, ROBOT).set_index("id")
    assert table.loc["a", "torque_over_samples"] == 0
    assert table.loc["b", "torque_over_samples"] == 3
    assert not table.loc["b", "ok"] and not table.loc["b", "physics_valid"]
    assert "physics" in table.loc["b", "error"]
    assert main(["export", "--check", str(tmp_path)]) == 1


def test_check_fails_a_file_with_other_gains(tmp_path) -> None:
    export_library([_traj("a")], tmp_path, "npz", robot=ROBOT)
    with np.load(tmp_path / "a.npz", allow_pickle=False) as z:
        kp = z["kp"] * 2
    _rewrite(tmp_path / "a.npz", kp=kp)
    row = check_library(tmp_path, ROBOT).iloc[0]
    assert not row["ok"] and "kp/kd" in row["error"]


def test_play_physics_shows_the_replay(tmp_path, capsys) -> None:
    export_library([_traj("a")], tmp_path, "npz", robot=ROBOT)
    out = tmp_path / "replay.gif"
    code = main(["play", str(tmp_path / "a.npz"), "--physics", "--format", "gif", "--out", str(out),
                 "--set", "render.preview_fps=3"])
    assert code == 0 and out.is_file() and out.stat().st_size > 0
    text = capsys.readouterr().out
    assert "physics:" in text and "torque over limit 0 samples" in text
