"""The pytorch-kinematics chain is built from MuJoCo's compiled model, on any MuJoCo version.

Why: pytorch-kinematics 0.10's `build_chain_from_mjcf` keys its joint-type map by `mjtJoint`
members, which numpy joint types of mujoco>=3.12 no longer hash equal to (`KeyError:
np.int32(3)` on every hinge). CI runs one MuJoCo version; these checks hold the adapter to the
behaviour the newer ones need wherever they run: the loader is never called, joint types are
read by value, and FK matches `mujoco.mj_kinematics`.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import pytorch_kinematics as pk
import torch

from embody.config.robot import RobotConfig
from embody.errors import ConfigError
from embody.robot import load_robot
from embody.robot.kinematics import Kinematics


def _broken_loader(*_args, **_kwargs):
    raise KeyError(np.int32(3))  # what pytorch-kinematics 0.10 raises on mujoco>=3.12


def test_chain_builds_without_pytorch_kinematics_mjcf_loader(monkeypatch):
    monkeypatch.setattr(pk, "build_chain_from_mjcf", _broken_loader)
    monkeypatch.setattr(pk.mjcf, "build_chain_from_mjcf", _broken_loader)
    robot = load_robot(RobotConfig(name="unitree_h1"))
    kin = Kinematics(robot.mjcf_path, robot.model, robot.spec.root_body, robot.joint_names)
    assert sorted(kin.chain.get_joint_parameter_names()) == sorted(robot.joint_names)

    rng = np.random.default_rng(1)
    qs = rng.uniform(robot.lower, robot.upper, size=(16, robot.n_joints))
    bodies = [robot.model.body(b).name for b in range(1, robot.model.nbody)
              if robot.model.body(b).name in kin.chain.frame_to_idx]
    got = kin.transforms(torch.tensor(qs), kin.frame_indices(bodies)).numpy()
    data = mujoco.MjData(robot.model)
    worst = 0.0
    for i, q in enumerate(qs):
        data.qpos[:] = robot.qpos(q)  # the root at its default pose, as the chain's root
        mujoco.mj_kinematics(robot.model, data)
        for k, name in enumerate(bodies):
            b = robot.model.body(name).id
            worst = max(worst, np.abs(got[i, k, :3, :3] - data.xmat[b].reshape(3, 3)).max(),
                        np.abs(got[i, k, :3, 3] - data.xpos[b]).max())
    assert worst < 1e-9


def test_joint_types_are_read_by_value():
    """MuJoCo's numpy joint types (np.int32) map to pk's types whatever the enum's hashing."""
    from embody.robot.kinematics import _JOINT_TYPES

    assert _JOINT_TYPES[int(np.int32(mujoco.mjtJoint.mjJNT_HINGE))] == "revolute"
    assert _JOINT_TYPES[int(np.int32(mujoco.mjtJoint.mjJNT_SLIDE))] == "prismatic"
    model = load_robot(RobotConfig(name="unitree_h1")).model
    hinges = model.jnt_type[model.jnt_type != mujoco.mjtJoint.mjJNT_FREE]
    assert hinges.dtype.kind == "i" and all(int(t) in _JOINT_TYPES for t in hinges)


def test_ball_joint_below_the_root_is_refused(tmp_path):
    xml = """<mujoco><worldbody><body name="root"><freejoint/>
      <geom size="0.1"/>
      <body name="a"><joint name="j" type="ball"/><geom size="0.05"/></body>
    </body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    with pytest.raises(ConfigError, match="hinge and slide"):
        Kinematics(tmp_path / "robot.xml", model, "root", ["j"])
