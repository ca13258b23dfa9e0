"""A robot definition's own `ik:` values: over the defaults, under the user's files and --set."""

from __future__ import annotations

import shutil

from embody.config import configs_dir, load_config
from embody.config.ik import IKConfig


def test_h1_ik_values_apply_and_the_user_wins() -> None:
    default = IKConfig()
    h1 = load_config(sets=["robot.name=unitree_h1"]).ik
    assert (h1.w_smooth, h1.w_wrist_rot) == (0.2, 0.005) != (default.w_smooth, default.w_wrist_rot)
    assert h1.w_wrist_pos == default.w_wrist_pos  # only what the robot names changes
    g1 = load_config().ik
    assert (g1.w_smooth, g1.w_wrist_rot) == (default.w_smooth, default.w_wrist_rot)
    user = load_config(sets=["robot.name=unitree_h1", "ik.w_smooth=0.05"]).ik
    assert (user.w_smooth, user.w_wrist_rot) == (0.05, 0.005)


def test_robot_ik_values_from_another_robots_dir(tmp_path) -> None:
    robots = tmp_path / "robots"
    robots.mkdir()
    text = (configs_dir() / "robots" / "unitree_h1.yaml").read_text()
    (robots / "mine.yaml").write_text(text.replace("ik: {w_smooth: 0.2, w_wrist_rot: 0.005}",
                                                   "ik: {iterations: 7}"))
    cfg = load_config(sets=["robot.name=mine", f"robot.robots_dir={robots}"])
    assert cfg.ik.iterations == 7 and cfg.ik.w_smooth == IKConfig().w_smooth
    from embody.robot.spec import read_spec
    assert read_spec(robots / "mine.yaml").ik == {"iterations": 7}
    shutil.rmtree(robots)  # a missing robot file is reported where the robot loads, not here
    assert load_config(sets=["robot.name=mine", f"robot.robots_dir={robots}"]).ik.iterations == IKConfig().iterations
