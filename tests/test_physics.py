"""Physics replay on a planted two-link arm: tracking, torque limits, saturation, verdicts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embody.errors import ConfigError
from embody.physics import actuation, commands, evaluate, replay_fixed
from embody.robot.model import build_robot
from embody.robot.spec import RobotSpec
from embody.verdicts import run_verdicts, sequence_verdicts, verdict_line

ARM = """
<mujoco>
  <worldbody>
    <body name="pelvis" pos="0 0 1">
      <freejoint/>
      <geom type="box" size=".1 .1 .1" mass="20" contype="0" conaffinity="0"/>
      <body name="torso" pos="0 0 0.3">
        <geom type="box" size=".05 .05 .05" mass="5" contype="0" conaffinity="0"/>
        <body name="upper" pos="0 0.2 0">
          <joint name="shoulder" axis="0 1 0" actuatorfrcrange="-{limit} {limit}" damping="0.1"/>
          <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1.5" contype="0" conaffinity="0"/>
          <body name="fore" pos="0.3 0 0">
            <joint name="elbow" axis="0 1 0" actuatorfrcrange="-{limit} {limit}" damping="0.1"/>
            <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="1" contype="0" conaffinity="0"/>
          </body>
        </body>
      </body>
      <body name="leg" pos="0 0 -0.9">
        <geom type="box" size=".12 .15 .02" mass="5" group="3"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _arm(tmp_path: Path, limit: float, kp: float, kd: float, rate: float = 500.0):
    path = tmp_path / f"arm_{limit}_{kp}.xml"
    path.write_text(ARM.replace("{limit}", str(limit)))
    spec = RobotSpec(
        mjcf={"path": str(path)}, root_body="pelvis", torso_body="torso",
        links={"left_wrist": {"body": "fore"}, "right_wrist": {"body": "fore"}},
        ik_joints=["*"], landmarks={"left_palm": {"body": "fore", "offset": [0.25, 0.0, 0.0]}},
        actuation={"groups": {"arm": {"joints": ["*"], "kp": kp, "kd": kd, "rate_hz": rate,
                                      "source": "test"}},
                   "stance": {"kp": 500.0, "kd": 10.0, "source": "test"}})
    return build_robot("arm", spec, path, str(path))


def _slow(fps: float = 50.0, seconds: float = 3.0) -> np.ndarray:
    t = np.arange(int(seconds * fps) + 1) / fps
    ramp = 0.5 * (1 - np.cos(np.pi * t / t[-1]))
    return np.stack([-0.4 * ramp + 0.1 * np.sin(2 * np.pi * 0.3 * t), 0.6 * ramp], axis=1)


def test_replay_tracks_a_feasible_trajectory_under_a_millimetre(tmp_path):
    robot = _arm(tmp_path, limit=100.0, kp=3000.0, kd=60.0, rate=1000.0)
    q = _slow()
    res = evaluate(robot, q, 50.0)
    m = res.metrics
    assert m["palm_err_max_mm"] < 1.0
    assert m["torque_over_samples"] == 0 and m["saturated_steps"] == 0
    assert m["sim_contact_samples"] == 0
    assert m["control_steps"] == 3001  # 3 s at 1 kHz, both ends
    # the simulated palm moved as far as the reference's (not a replay that stood still)
    travel = np.abs(res.arrays["q_sim"][-1] - res.arrays["q_sim"][0])
    np.testing.assert_allclose(travel, np.abs(q[-1] - q[0]), atol=2e-3)


def test_low_gains_track_worse_than_high_gains(tmp_path):
    q = _slow()
    soft = evaluate(_arm(tmp_path, limit=100.0, kp=20.0, kd=1.0), q, 50.0).metrics
    stiff = evaluate(_arm(tmp_path, limit=100.0, kp=2000.0, kd=40.0), q, 50.0).metrics
    assert soft["palm_err_p95_mm"] > 3 * stiff["palm_err_p95_mm"]


def test_torque_over_the_limit_is_counted_and_saturates(tmp_path):
    # holding the 0.55 m arm horizontal needs ~ (1.5·0.15 + 1·0.425)·9.81 ≈ 6.4 N·m at the shoulder
    robot = _arm(tmp_path, limit=3.0, kp=80.0, kd=3.0)
    q = np.zeros((100, 2))
    cmd = commands(robot, q, 50.0)
    assert np.abs(cmd.tau_ff[:, 0]).min() == pytest.approx(6.4, abs=0.2)
    m = evaluate(robot, q, 50.0, cmd=cmd).metrics
    assert m["torque_over_samples"] == 100
    assert m["saturated_step_pct"] == pytest.approx(100.0)
    assert m["torque_ratio_max"] == pytest.approx(6.4 / 3.0, abs=0.1)
    assert m["valid"] is False
    fixed = replay_fixed(robot, cmd)
    assert np.abs(fixed.rollout.torque).max() <= 3.0 + 1e-9  # the motor never gives more than its limit
    assert fixed.q50[-1, 0] > 0.3  # and the arm sags under gravity (pitch axis y: down is +)


def test_actuation_must_cover_every_joint(tmp_path):
    robot = _arm(tmp_path, limit=10.0, kp=80.0, kd=3.0)
    groups = {"arm": {"joints": ["shoulder"], "kp": 80.0, "kd": 3.0, "rate_hz": 250.0, "source": "x"}}
    spec = robot.spec.model_copy(update={"actuation": robot.spec.actuation.model_copy(
        update={"groups": {k: robot.spec.actuation.groups["arm"].model_copy(update=v) for k, v in groups.items()}})})
    other = build_robot("arm", spec, robot.mjcf_path, str(robot.mjcf_path))
    with pytest.raises(ConfigError, match="elbow"):
        actuation(other)


def _seq(status="ok", physics=None, valid=True):
    metrics = {"metrics": {"joint_limit_violations": 0, "velocity_violations": 0,
                           "self_collision_frames": 0 if valid else 2, "torque_viol": 0}}
    if physics is not None:
        metrics["physics"] = physics
    return {"status": status, "metrics": metrics}


GOOD = {"torque_over_samples": 0, "saturated_steps": 0, "palm_err_p95_mm": 4.0,
        "sim_contact_samples": 0, "zmp_margin_min_mm": 35.0, "standing_holds": True}


def test_four_verdicts():
    bad_zmp = {**GOOD, "zmp_margin_min_mm": 12.0}
    bad_torque = {**GOOD, "torque_over_samples": 3}
    rows = [sequence_verdicts(s) for s in (_seq(physics=GOOD), _seq(physics=bad_zmp),
                                          _seq(physics=bad_torque, valid=False),
                                          _seq(status="failed", physics=GOOD), _seq())]
    assert [r["physics_valid"] for r in rows] == [True, False, False, False, None]
    assert [r["export_valid"] for r in rows] == [True, True, False, False, True]
    counts = run_verdicts(rows)
    assert {k: counts[k] for k in ("total", "processed_ok", "export_valid", "critic_accepted",
                                    "physics_valid")} == {"total": 5, "processed_ok": 4, "export_valid": 3,
                                                          "critic_accepted": None, "physics_valid": 1}
    assert verdict_line(counts).endswith("1/5 physics-valid")
    missing = {k: v for k, v in GOOD.items() if k != "standing_holds"}
    assert sequence_verdicts(_seq(physics=missing))["physics_valid"] is False
    skipped = {"skipped": "the robot YAML has no actuation section"}
    assert sequence_verdicts(_seq(physics=skipped))["physics_valid"] is None


def test_standing_holds_still_and_tips_under_a_violent_swing(tmp_path):
    robot = _arm(tmp_path, limit=100.0, kp=3000.0, kd=60.0, rate=1000.0)
    still = evaluate(robot, np.zeros((100, 2)), 50.0).metrics
    assert still["standing_holds"] and still["zmp_margin_min_mm"] > 50.0
    assert still["standing_pelvis_tilt_max_deg"] < 1.0
    # the 2.5 kg arm whipped up and down at 3 Hz through 1.2 rad: the ZMP leaves the 0.24 m foot
    t = np.arange(150) / 50.0
    swing = np.stack([-1.2 * np.abs(np.sin(2 * np.pi * 1.5 * t)), np.zeros_like(t)], axis=1)
    fast = evaluate(robot, swing, 50.0).metrics
    assert fast["zmp_margin_min_mm"] < 0.0
    # and the simulated robot agrees: a foot lifts and the body slides
    assert not fast["standing_holds"] and fast["standing_foot_lift_max_mm"] > 5.0


def test_the_reference_holds_each_groups_command_at_its_rate(tmp_path):
    from embody.physics.replay import reference
    robot = _arm(tmp_path, limit=100.0, kp=300.0, kd=6.0, rate=500.0)
    groups = {"shoulder": {"joints": ["shoulder"], "kp": 300.0, "kd": 6.0, "rate_hz": 500.0, "source": "x"},
              "elbow": {"joints": ["elbow"], "kp": 300.0, "kd": 6.0, "rate_hz": 100.0, "source": "x"}}
    spec = robot.spec.model_copy(update={"actuation": robot.spec.actuation.model_copy(
        update={"groups": {k: robot.spec.actuation.groups["arm"].model_copy(update=v) for k, v in groups.items()}})})
    robot = build_robot("arm2", spec, robot.mjcf_path, str(robot.mjcf_path))
    q = _slow(seconds=1.0)
    cmd = commands(robot, q, 50.0)
    ref = reference(robot, cmd)
    assert ref.dt == pytest.approx(1 / 500.0) and len(ref.q) == 501  # 1 s at the fastest rate, both ends
    # the 100 Hz elbow changes every 5th step only, the 500 Hz shoulder every step
    assert (np.diff(ref.q[:, 1]) != 0).sum() == 100
    assert (np.diff(ref.q[:, 0]) != 0).sum() == 500
    # at the 50 Hz samples both are the commands themselves
    k = np.arange(0, 501, 10)
    np.testing.assert_allclose(ref.q[k], cmd.q, atol=1e-12)
    np.testing.assert_allclose(ref.qd[k], cmd.qd, atol=1e-9)
    np.testing.assert_allclose(ref.tau[k], cmd.tau_ff, atol=1e-9)
    # between samples: the Hermite spline (shoulder at 3 ms) and the linear feed-forward
    t = 3 * ref.dt
    from scipy.interpolate import CubicHermiteSpline
    spline = CubicHermiteSpline(cmd.times, cmd.q, cmd.qd, axis=0)
    assert ref.q[3, 0] == pytest.approx(spline(t)[0], abs=1e-12)
    assert ref.q[3, 1] == pytest.approx(cmd.q[0, 1], abs=1e-12)  # the elbow's 0 ms command, held
    assert ref.tau[3, 0] == pytest.approx(0.7 * cmd.tau_ff[0, 0] + 0.3 * cmd.tau_ff[1, 0], abs=1e-9)
