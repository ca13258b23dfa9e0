"""The low-level commands a robot stack sends per 50 Hz sample: what `embody export` writes and
what the physics replay plays (one rule for both).

The reference between samples is the natural cubic spline through them: q̇ is its slope at each
sample, so a player that interpolates (q, q̇) with a cubic Hermite spline (the replay, a Unitree
stack's interpolator) plays exactly that curve, and the feed-forward torque is the inverse
dynamics of that curve at the samples (`dynamics.spline_derivatives`): the torque the retarget
solve holds within the limits, so the motors' PD only corrects small tracking errors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from embody.physics.actuation import actuation
from embody.robot.dynamics import inverse_dynamics, spline_derivatives
from embody.robot.model import Robot


@dataclass(frozen=True)
class Commands:
    """Per sample (T,n): joint target q, its velocity qd (the natural cubic spline's slope), the
    feed-forward torque tau_ff (fixed-base free-motion inverse dynamics of that spline: gravity,
    Coriolis and inertia), and per joint (n,) the PD gains kp, kd. A Unitree `LowCmd` motor
    command takes exactly these five per motor."""

    fps: float
    q: np.ndarray
    qd: np.ndarray
    tau_ff: np.ndarray
    kp: np.ndarray
    kd: np.ndarray

    @property
    def times(self) -> np.ndarray:
        return np.arange(len(self.q)) / self.fps


def commands(robot: Robot, q: np.ndarray, fps: float) -> Commands:
    """Commands for joint samples q (T,n) at `fps` Hz with the robot's gains."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    dt = 1.0 / fps
    qd, qdd = spline_derivatives(q, dt)
    tau = inverse_dynamics(robot, q, dt, qd, qdd)
    act = actuation(robot)
    return Commands(fps=float(fps), q=q, qd=qd, tau_ff=tau, kp=act.kp.copy(), kd=act.kd.copy())
