"""The control-rate dynamics limits: a trajectory over a motor's effort limit or out of the feet's
support polygon is retimed (slowed down where it fails, its path kept), a feasible one is left as
it is, and validation counts what is left over (`torque_viol`), which the export refuses."""

from __future__ import annotations

import numpy as np
import pytest

from embody.config import Config
from embody.retarget.dynamics_limits import DynamicsLimits, duration_ratio, retime_dynamics, time_stretch
from embody.retarget.limits import limit_violations, velocity_violations
from embody.retarget.validation import validation_counts
from embody.robot import load_robot
from embody.robot.contacts import self_collision_contacts
from embody.robot.dynamics import effort_limits, inverse_dynamics, zmp
from scipy.interpolate import CubicSpline
from embody.verdicts import export_valid, violations

RATE = 50.0


@pytest.fixture(scope="module")
def robot():
    return load_robot(Config().robot)


def _planted(robot, scale: float = 1.0) -> np.ndarray:
    """Arms at the T-pose; the left shoulder pitch reverses at its full speed (× `scale`) for a few
    samples (within the velocity limit): the hand's reaction loads the wrist pitch far past its
    5 N·m."""
    t = 120
    q = np.tile(robot.tpose, (t, 1))
    j = robot.joint_index("left_shoulder_pitch_joint")
    step = scale * 0.98 * robot.velocity_limits[j] / RATE
    zig = np.zeros(t)
    for k in range(60, 66):
        zig[k] = zig[k - 1] + (step if k % 2 else -step)
    zig[66:] = zig[65]
    q[:, j] += zig
    return q


def _on_path(q: np.ndarray, out: np.ndarray, source_time: np.ndarray) -> float:
    """Largest distance (rad) of the retimed samples from the input's path: the natural cubic
    spline through the input samples, read at each sample's source time."""
    path = CubicSpline(np.arange(len(q), dtype=np.float64), q, bc_type="natural")
    return float(np.abs(path(source_time * RATE) - out).max())


def _timing_checks(q: np.ndarray, timed) -> None:
    st = timed.source_time
    assert len(st) == len(timed.q) and st[0] == 0.0
    assert (np.diff(st) > 0).all()  # monotone: the motion never runs backwards in the source's time
    assert abs(st[-1] - (len(q) - 1) / RATE) < 1e-9  # the whole source, to its last sample
    assert np.diff(st).max() <= 1.0 / RATE + 1e-9  # slowed down, never sped up


def test_wrist_over_its_effort_limit_is_repaired(robot):
    q = _planted(robot)
    limit = effort_limits(robot)
    wrist = robot.joint_index("left_wrist_pitch_joint")
    before = np.abs(inverse_dynamics(robot, q, 1 / RATE)) / limit
    assert before[:, wrist].max() > 1.2  # the plant really asks the wrist for more than it has
    assert validation_counts(robot, q, RATE)["torque_viol"] > 0
    limits = DynamicsLimits(torque_fraction=0.9, zmp_margin=0.02)
    timed = retime_dynamics(robot, q, RATE, limits)
    out = timed.q
    ratio = np.abs(inverse_dynamics(robot, out, 1 / RATE)) / limit
    assert timed.ok
    assert ratio.max() <= 1.0  # every joint, fingers included, within its limit
    assert _need(robot, out).max() <= 1.0
    _, _, margin = zmp(robot, out, 1 / RATE)
    assert margin.min() >= 0.02 - 1e-6
    assert velocity_violations(out, robot.velocity_limits, RATE) == 0
    assert limit_violations(out, robot.lower, robot.upper) == 0
    assert (self_collision_contacts(robot, out) == 0).all()
    counts = validation_counts(robot, out, RATE)
    assert counts["torque_viol"] == 0 and export_valid(counts)
    # the path is kept: every sample lies on the input's spline at its source time
    _timing_checks(q, timed)
    assert timed.contact_samples == 0 and _on_path(q, out, timed.source_time) < 1e-9
    # the slowdown is local: samples over a second from the reversal are the input's own
    assert np.array_equal(out[:10], q[:10]) and np.array_equal(out[-10:], q[-10:])
    assert time_stretch(timed.source_time, RATE) > 1.5  # the reversal really was slowed down
    assert 1.0 < duration_ratio(timed.source_time, RATE) < 2.0


def test_solved_trajectory_replays_without_saturating(robot):
    """The torque the solve holds is the torque of the curve the robot is commanded along (the
    spline of `physics.commands`): replayed in MuJoCo at the G1's gains, no motor saturates,
    where the planted input saturates the wrist."""
    from embody.physics import commands
    from embody.physics.replay import replay_fixed

    def saturated(q: np.ndarray) -> int:
        r = replay_fixed(robot, commands(robot, q, RATE)).rollout
        return int((np.abs(r.demand) >= r.limit * (1 - 1e-9)).any(1).sum())

    q = _planted(robot)
    assert saturated(q) > 0
    timed = retime_dynamics(robot, q, RATE, DynamicsLimits())
    assert timed.ok
    assert saturated(timed.q) == 0


def test_feasible_motion_is_unchanged(robot):
    t = np.arange(100) / RATE
    q = np.tile(robot.tpose, (len(t), 1))
    for name in ("left_shoulder_pitch_joint", "right_elbow_joint", "left_wrist_pitch_joint"):
        q[:, robot.joint_index(name)] += 0.2 * np.sin(2 * np.pi * 0.5 * t)
    ratio = np.abs(inverse_dynamics(robot, q, 1 / RATE)) / effort_limits(robot)
    assert ratio.max() < 0.9
    assert zmp(robot, q, 1 / RATE)[2].min() > 0.02
    timed = retime_dynamics(robot, q, RATE, DynamicsLimits())
    assert timed.ok
    assert np.array_equal(timed.q, q)
    np.testing.assert_array_equal(timed.source_time, np.arange(len(q)) / RATE)


def _need(robot, q: np.ndarray) -> np.ndarray:
    """(T,n) what the replay asks of each motor over its limit: the exported feed-forward plus
    the PD's lag share (kd·|q̈|/rate)."""
    from embody.physics.actuation import actuation
    from embody.robot.dynamics import spline_derivatives

    act = actuation(robot)
    _, qdd = spline_derivatives(q, 1 / RATE)
    return (np.abs(inverse_dynamics(robot, q, 1 / RATE)) + act.kd / act.rate_hz * np.abs(qdd)) / act.limit


def test_motion_inside_the_limits_but_not_the_margin_is_unchanged(robot):
    """The planted reversal, slowed until the motors' need peaks at 95 % of a limit (past
    `torque_fraction` 0.9, inside the limit itself): the validation counts nothing and the replay
    does not saturate, so the solve leaves it exactly as it is (its margin applies only where it
    must act)."""
    from embody.physics import commands
    from embody.physics.replay import replay_fixed

    low, high = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if _need(robot, _planted(robot, mid)).max() < 0.95 else (low, mid)
    q = _planted(robot, low)
    need = _need(robot, q).max()
    assert 0.93 < need < 0.97
    assert validation_counts(robot, q, RATE)["torque_viol"] == 0
    r = replay_fixed(robot, commands(robot, q, RATE)).rollout
    assert not (np.abs(r.demand) >= r.limit * (1 - 1e-9)).any()
    assert zmp(robot, q, 1 / RATE)[2].min() > 0.0  # inside the feet (this test's ZMP margin: 0)
    timed = retime_dynamics(robot, q, RATE, DynamicsLimits(torque_fraction=0.9, zmp_margin=0.0))
    assert timed.ok
    assert np.array_equal(timed.q, q) and len(timed.source_time) == len(q)


def test_zmp_out_of_the_feet_is_brought_back(robot):
    """Both arms swung forward and back together at speed: the upper body's reaction throws the
    cart-table ZMP out of the feet; the solve brings it 20 mm inside."""
    t = np.arange(80) / RATE
    q = np.tile(robot.tpose, (len(t), 1))
    for name in ("left_shoulder_pitch_joint", "right_shoulder_pitch_joint"):
        j = robot.joint_index(name)
        q[:, j] += 0.9 * robot.velocity_limits[j] / (2 * np.pi * 2.0) * np.sin(2 * np.pi * 2.0 * t)
    _, _, before = zmp(robot, q, 1 / RATE)
    assert before.min() < 0.0
    timed = retime_dynamics(robot, q, RATE, DynamicsLimits(zmp_margin=0.02))
    _, _, after = zmp(robot, timed.q, 1 / RATE)
    assert timed.ok
    assert after.min() >= 0.02 - 1e-6
    assert velocity_violations(timed.q, robot.velocity_limits, RATE) == 0
    _timing_checks(q, timed)
    assert _on_path(q, timed.q, timed.source_time) < 1e-9


def test_export_refuses_torque_violations():
    counters = {"joint_limit_violations": 0, "velocity_violations": 0, "self_collision_frames": 0,
                "torque_viol": 3}
    assert not export_valid(counters)
    assert violations(counters) == {"torque_viol": 3}
    assert not export_valid({k: v for k, v in counters.items() if k != "torque_viol"})  # unmeasured


def test_two_handed_excerpt_is_repaired_without_contacts(robot):
    """1.4 s of a retargeted two-handed sign's kinematic 50 Hz export (synth seq 0, samples
    100-169: the contact repair keeps the hands 2 mm apart while the arms zig-zag): its motors
    are asked for more than their limits, and between its samples the spline the robot plays
    passes through the other hand. Retimed, every sample's need is within its limit, the ZMP
    inside its margin, no counted pair closer than the export's gap (the samples the slowdown
    puts between the input's, pushed clear where they touched), the velocity limits kept, and
    the path is the input's but for those pushes."""
    from pathlib import Path

    from embody.retarget.limits import EXPORT_GAP
    from embody.robot.contacts import near_contacts

    data = np.load(Path(__file__).parent / "data" / "g1_two_hands_kinematic_50hz.npz")
    assert list(data["joint_names"]) == list(robot.joint_names)
    q = data["q"]
    assert (near_contacts(robot, q, EXPORT_GAP) == 0).all()
    assert _need(robot, q).max() > 2.0
    timed = retime_dynamics(robot, q, RATE, DynamicsLimits())
    out = timed.q
    assert timed.ok
    assert _need(robot, out).max() <= 1.0
    assert zmp(robot, out, 1 / RATE)[2].min() >= 0.02 - 1e-6
    assert (near_contacts(robot, out, EXPORT_GAP) == 0).all()
    assert velocity_violations(out, robot.velocity_limits, RATE) == 0
    assert limit_violations(out, robot.lower, robot.upper) == 0
    _timing_checks(q, timed)
    assert timed.contact_samples > 0  # the spline between the input's samples did touch
    # each push within its 10° trust radius of the path it moves; the contact rounds add up
    assert _on_path(q, out, timed.source_time) < np.radians(20)
    assert duration_ratio(timed.source_time, RATE) < 4.0


def test_hands_passing_through_each_other_between_samples_are_cleared(robot):
    """The whole kinematic 50 Hz export of synth seq 15 (default G1 run): every sample clear,
    but between samples 77 and 78 (and again over 119-122) the spline the robot plays takes one
    wrist 45 mm through the other hand, right where the arms zig-zag past their torque limits
    and the ZMP leaves the feet. Retimed, the samples the slowdown puts there are pushed clear
    (the pushes a displacement of the path, retimed from the input's own timing): every limit
    holds, no sample penetrates, and the slowdown stays bounded."""
    from pathlib import Path

    from embody.retarget.control import BOX_MARGIN, VELOCITY_MARGIN

    data = np.load(Path(__file__).parent / "data" / "g1_hands_pass_through_kinematic_50hz.npz")
    assert list(data["joint_names"]) == list(robot.joint_names)
    q = data["q"]
    assert (self_collision_contacts(robot, q) == 0).all()
    path = CubicSpline(np.arange(len(q), dtype=np.float64), q, bc_type="natural")
    assert (self_collision_contacts(robot, path(np.linspace(77.0, 78.0, 9))) > 0).any()  # tunnels
    assert _need(robot, q).max() > 1.0
    timed = retime_dynamics(robot, q, RATE, DynamicsLimits(), box_margin=BOX_MARGIN,
                            velocity_margin=VELOCITY_MARGIN)
    out = timed.q
    assert timed.ok and len(out) > len(q)  # retimed, not the input kept
    assert _need(robot, out).max() <= 1.0
    assert zmp(robot, out, 1 / RATE)[2].min() >= 0.02 - 1e-6
    assert (self_collision_contacts(robot, out) == 0).all()
    assert velocity_violations(out, robot.velocity_limits, RATE) == 0
    assert limit_violations(out, robot.lower, robot.upper) == 0
    _timing_checks(q, timed)
    assert timed.contact_samples > 0
    assert duration_ratio(timed.source_time, RATE) < 3.0
