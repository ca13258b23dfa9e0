"""Inverse dynamics, effort limits and ZMP against hand computations on a planted model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embody.robot.dynamics import (GRAVITY, derivatives, effort_limits, inverse_dynamics, polygon_margin,
                                   spline_derivatives, torque_ratio, zmp)
from embody.robot.model import build_robot
from embody.robot.spec import RobotSpec

M, L, R, ARM = 2.0, 0.5, 0.02, 0.01  # pendulum bob mass, length, radius; joint armature

PENDULUM = f"""
<mujoco>
  <option gravity="0 0 -{GRAVITY}"/>
  <worldbody>
    <body name="pelvis" pos="0 0 1">
      <freejoint/>
      <geom type="box" size=".05 .05 .05" mass="10" contype="0" conaffinity="0"/>
      <body name="torso">
        <geom type="box" size=".02 .02 .02" mass="1" contype="0" conaffinity="0"/>
        <body name="arm">
          <joint name="swing" axis="0 1 0" armature="{ARM}" actuatorfrcrange="-5 5"/>
          <geom type="sphere" size="{R}" pos="0 0 -{L}" mass="{M}"/>
        </body>
        <body name="hand">
          <joint name="free_spin" axis="1 0 0"/>
          <geom type="sphere" size="0.01" mass="0.1" contype="0" conaffinity="0"/>
        </body>
      </body>
      <body name="leg" pos="0 0 -0.1">
        <geom type="box" size=".1 .05 .01" pos="0 0 -0.01" group="3"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    path = Path(tmp_path_factory.mktemp("pendulum")) / "pendulum.xml"
    path.write_text(PENDULUM)
    spec = RobotSpec(mjcf={"path": str(path)}, root_body="pelvis", torso_body="torso",
                     links={"left_wrist": {"body": "arm"}, "right_wrist": {"body": "hand"}},
                     ik_joints=["*"])
    return build_robot("pendulum", spec, path, str(path))


def test_effort_limits_from_mjcf(pendulum):
    lim = effort_limits(pendulum)
    assert pendulum.joint_names == ["swing", "free_spin"]
    assert lim[0] == pytest.approx(5.0) and np.isinf(lim[1])


def test_inverse_dynamics_matches_pendulum_equation(pendulum):
    dt = 0.002
    t = np.arange(400) * dt
    theta = 0.8 * np.sin(2 * np.pi * 1.5 * t)
    q = np.stack([theta, np.zeros_like(theta)], axis=1)
    tau = inverse_dynamics(pendulum, q, dt)
    _, qdd = spline_derivatives(q, dt)
    # the spline's acceleration is the motion's own, away from the natural ends
    exact = -(2 * np.pi * 1.5) ** 2 * theta
    np.testing.assert_allclose(qdd[50:-50, 0], exact[50:-50], atol=1e-4 * np.abs(exact).max())
    inertia = M * L**2 + 0.4 * M * R**2 + ARM
    # the bob hangs at (−L sinθ, 0, −L cosθ): gravity pulls it back with torque m g L sinθ
    expected = inertia * qdd[:, 0] + M * GRAVITY * L * np.sin(theta)
    np.testing.assert_allclose(tau[:, 0], expected, atol=1e-6 * np.abs(expected).max())
    np.testing.assert_allclose(tau[:, 1], 0.0, atol=1e-9)
    ratio = torque_ratio(pendulum, tau)
    assert ratio[:, 0].max() == pytest.approx(np.abs(expected).max() / 5.0, rel=1e-6)


def test_spline_derivatives_are_the_natural_cubic_spline():
    from scipy.interpolate import CubicSpline
    dt = 0.02
    rng = np.random.default_rng(3)
    q = np.cumsum(rng.normal(size=(40, 3)), axis=0) * 0.01
    qd, qdd = spline_derivatives(q, dt)
    ref = CubicSpline(np.arange(40) * dt, q, axis=0, bc_type="natural")
    t = np.arange(40) * dt
    np.testing.assert_allclose(qd, ref(t, 1), atol=1e-9)
    np.testing.assert_allclose(qdd, ref(t, 2), atol=1e-6)
    # a 50 Hz zig-zag: the curve through it accelerates 3x what central differences say
    zig = ((-1.0) ** np.arange(41) * 1e-3)[:, None]
    _, a = spline_derivatives(zig, dt)
    _, c = derivatives(zig, dt)
    assert abs(a[20, 0]) == pytest.approx(3.0 * abs(c[20, 0]), rel=1e-3)


def test_derivatives_central_inside_one_sided_at_ends():
    dt = 0.1
    q = (np.arange(6, dtype=float) ** 2)[:, None] * dt**2  # q = t², qd = 2t, qdd = 2
    qd, qdd = derivatives(q, dt)
    np.testing.assert_allclose(qd[1:-1, 0], 2 * np.arange(1, 5) * dt)
    assert qd[0, 0] == pytest.approx((q[1, 0] - q[0, 0]) / dt)
    np.testing.assert_allclose(qdd[:, 0], 2.0)


def test_polygon_margin_signed():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    m = polygon_margin(np.array([[0.5, 0.5], [0.9, 0.5], [1.5, 0.5], [2.0, 2.0]]), square)
    np.testing.assert_allclose(m, [0.5, 0.1, -0.5, -np.sqrt(2)])


def test_zmp_static_is_com_and_moves_against_acceleration(pendulum):
    dt = 0.02
    still = np.zeros((20, 2))
    point, poly, margin = zmp(pendulum, still, dt)
    # the box under the "leg" is the foot: 0.2 × 0.1 m around the pelvis's xy
    assert poly[:, 0].max() - poly[:, 0].min() == pytest.approx(0.2, abs=1e-9)
    np.testing.assert_allclose(point - point[0], 0.0, atol=1e-12)
    assert margin[0] > 0
    t = np.arange(50) * dt
    swing = np.stack([0.5 * np.sin(2 * np.pi * 2 * t), np.zeros_like(t)], axis=1)
    moving, _, m2 = zmp(pendulum, swing, dt)
    assert np.ptp(moving[:, 0]) > 0.05 and m2.min() < margin[0]
