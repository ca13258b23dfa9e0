"""A robot's motor control per joint: PD gains and command rate (YAML), effort limit (MJCF)."""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass

import numpy as np

from embody.errors import ConfigError
from embody.robot.dynamics import effort_limits, leg_joints
from embody.robot.model import Robot


@dataclass(frozen=True)
class Actuation:
    """Per joint (robot.joint_names order): gains, command rate, effort limit and group."""

    kp: np.ndarray  # (n,) N·m/rad
    kd: np.ndarray  # (n,) N·m·s/rad
    rate_hz: np.ndarray  # (n,)
    limit: np.ndarray  # (n,) N·m, inf where the MJCF sets none
    group: np.ndarray  # (n,) int index into group_names
    group_names: list[str]

    @property
    def control_rate_hz(self) -> float:
        """The fastest group's command rate: the replay's physics step."""
        return float(self.rate_hz.max())


def actuation(robot: Robot) -> Actuation:
    """The robot's `actuation:` section resolved per joint (first matching group wins); cached
    on the robot. ConfigError naming the YAML key when it is missing or leaves a joint out."""
    key = "physics.actuation"
    if key in robot.derived:
        return robot.derived[key]
    where = f"{robot.name}.yaml:actuation"
    spec = robot.spec.actuation
    if spec is None or not spec.groups:
        raise ConfigError(where, "no actuation groups: physics replay needs gains per joint")
    names = list(spec.groups)
    group = np.full(robot.n_joints, -1)
    for j, joint in enumerate(robot.joint_names):
        for g, gains in enumerate(spec.groups.values()):
            if any(fnmatch.fnmatchcase(joint, p) for p in gains.joints):
                group[j] = g
                break
    missing = [n for n, g in zip(robot.joint_names, group) if g < 0]
    if missing:
        raise ConfigError(f"{where}.groups", f"no group matches joints {missing}")
    if spec.stance is not None:
        legs = leg_joints(robot)
        for name in spec.stance.pose:
            if name not in robot.joint_names or not legs[robot.joint_index(name)]:
                raise ConfigError(f"{where}.stance.pose.{name}", "not a leg joint of this robot")
    gains = list(spec.groups.values())
    out = Actuation(kp=np.array([gains[g].kp for g in group]), kd=np.array([gains[g].kd for g in group]),
                    rate_hz=np.array([gains[g].rate_hz for g in group]), limit=effort_limits(robot),
                    group=group, group_names=names)
    robot.derived[key] = out
    return out
