"""`robot`: settings of the robot stage."""

from __future__ import annotations

from embody.config.base import Section


class RobotConfig(Section):
    pass
