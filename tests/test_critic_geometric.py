"""The geometric critic: emits the primitives that cancel measured offsets, accepts small ones."""

import numpy as np

from embody.config.critic import CriticConfig
from embody.critic.action import Limits
from embody.critic.base import CritiqueContext
from embody.critic.geometric import GeometricCritic
from embody.critic.primitives import Primitive, apply_primitives, axis_angle_matrix

T, FPS, ARM = 60, 30.0, 0.45


def _context(robot_pos, robot_rot, ref_pos, ref_rot):
    return CritiqueContext(0, FPS, ARM, ref_pos, ref_rot, robot_pos, robot_rot, Limits(T))


def _reference():
    t = np.linspace(0, 2 * np.pi, T)
    pos = np.zeros((T, 2, 3))
    pos[:, 0] = np.stack([0.25 + 0.05 * np.sin(t), 0.2 + 0.03 * np.cos(t), 0.1 + 0 * t], 1)
    pos[:, 1] = np.stack([0.25 + 0 * t, -0.2 + 0.05 * np.sin(t), 0.15 + 0 * t], 1)
    return pos, np.tile(np.eye(3), (T, 2, 1, 1))


def test_recovers_a_whole_sequence_offset_exactly():
    ref_pos, ref_rot = _reference()
    robot_pos = ref_pos.copy()
    robot_pos[:, 0, 2] += 0.10   # left hand 10 cm too high
    robot_pos[:, 1, 1] -= 0.06   # right hand 6 cm too far out (−y)
    action = GeometricCritic(CriticConfig()).critique(_context(robot_pos, ref_rot, ref_pos, ref_rot))
    assert action.valid and action.verdict == "revise"
    assert set(action.primitives) == {Primitive("move_left_down", 0.10), Primitive("move_right_in", 0.06)}
    fixed, _ = apply_primitives(robot_pos, ref_rot, action.primitives, blend_frames=0)
    np.testing.assert_allclose(fixed, ref_pos, atol=1e-9)


def test_uses_the_worst_window_when_it_stands_out():
    ref_pos, ref_rot = _reference()
    robot_pos = ref_pos.copy()
    robot_pos[20:35, 1, 0] -= 0.12  # right hand 12 cm too far back for half a second
    action = GeometricCritic(CriticConfig(window_s=0.5)).critique(
        _context(robot_pos, ref_rot, ref_pos, ref_rot))
    (prim,) = action.primitives
    assert prim.name == "move_right_forward" and prim.amount == 0.12
    start, end = prim.window
    assert end - start + 1 == 15 and 20 <= start and end <= 34


def test_yaw_offset_gives_a_yaw_primitive():
    ref_pos, ref_rot = _reference()
    robot_rot = ref_rot.copy()
    # the robot's left hand is turned 25° about +z (toward +y: outward for the left hand)
    robot_rot[:, 0] = axis_angle_matrix(np.array([0, 0, 1.0]), np.full(T, np.radians(25))) @ ref_rot[:, 0]
    action = GeometricCritic(CriticConfig()).critique(_context(ref_pos, robot_rot, ref_pos, ref_rot))
    assert action.primitives == (Primitive("left_yaw_in", 25.0),)
    _, fixed = apply_primitives(ref_pos, robot_rot, action.primitives, blend_frames=0)
    np.testing.assert_allclose(fixed, ref_rot, atol=1e-9)


def test_accepts_below_thresholds_and_is_deterministic():
    ref_pos, ref_rot = _reference()
    robot_pos = ref_pos + 0.004  # 4 mm per axis: below 3% of the arm
    critic = GeometricCritic(CriticConfig())
    a = critic.critique(_context(robot_pos, ref_rot, ref_pos, ref_rot))
    b = critic.critique(_context(robot_pos, ref_rot, ref_pos, ref_rot))
    assert a.accepted and a.primitives == () and a == b
