"""Physics replay of exported trajectories: does the robot execute them within its motors' limits?

`actuation` reads each robot's PD gains and command rates (YAML) and effort limits (MJCF);
`commands` turns a 50 Hz joint array into the low-level commands a robot stack sends (q, q̇,
feed-forward torque, kp, kd); `replay` runs them in MuJoCo, pelvis welded and standing on the
floor; `evaluate` measures the replay and states the physics-valid verdict's inputs.
"""

from __future__ import annotations

from embody.physics.actuation import Actuation, actuation
from embody.physics.commands import Commands, commands
from embody.physics.evaluate import PhysicsResult, evaluate
from embody.physics.replay import FixedBaseReplay, StandingReplay, replay_fixed, replay_standing

__all__ = ["Actuation", "actuation", "Commands", "commands", "FixedBaseReplay", "StandingReplay",
           "replay_fixed", "replay_standing", "PhysicsResult", "evaluate"]
