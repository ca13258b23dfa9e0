"""`robot`: which robot to retarget to."""

from __future__ import annotations

from pydantic import Field

from embody.config.base import Section


class RobotConfig(Section):
    #: A robot definition `configs/robots/<name>.yaml` (or under `robots_dir`).
    name: str = Field("unitree_g1_dex3", min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    #: Override the MJCF file of the robot definition (same kinematic tree expected).
    mjcf_path: str | None = None
    #: Directory of robot definitions; default `configs/robots`.
    robots_dir: str | None = None
