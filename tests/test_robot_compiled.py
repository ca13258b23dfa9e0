"""`embody.robot.compiled`: the MJCF compiled once and kept as MJB, reloaded exactly, and
compiled again whenever the MJCF or a file beside it changes."""

from __future__ import annotations

import os

import mujoco
import numpy as np
import pytest

from embody.robot.compiled import compiled_model, model_key

MJCF = """<mujoco>
  <compiler angle="radian" meshdir="assets"/>
  <asset><mesh name="box" file="box.obj"/></asset>
  <worldbody>
    <body name="link"><joint name="hinge" type="hinge" range="-1 1"/>
      <geom type="mesh" mesh="box"/></body>
  </worldbody>
</mujoco>
"""
BOX = """v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"""


@pytest.fixture
def robot_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("EMBODY_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "robot"
    (folder / "assets").mkdir(parents=True)
    (folder / "assets" / "box.obj").write_text(BOX)
    (folder / "robot.xml").write_text(MJCF)
    return folder


def _arrays(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    return {n: getattr(model, n) for n in dir(model)
            if not n.startswith("_") and isinstance(getattr(model, n, None), np.ndarray)}


def test_the_cached_model_is_the_compiled_one(robot_dir, tmp_path):
    mjcf = robot_dir / "robot.xml"
    first = compiled_model(mjcf)
    cached = list((tmp_path / "cache" / "mujoco").glob("robot-*.mjb"))
    assert len(cached) == 1 and cached[0].stem == f"robot-{model_key(mjcf)}"
    again = compiled_model(mjcf)  # from the MJB
    reference = mujoco.MjModel.from_xml_path(str(mjcf))
    ref = _arrays(reference)
    for name, value in _arrays(again).items():
        np.testing.assert_array_equal(value, ref[name], err_msg=name)
    assert again.mesh_vertnum.tolist() == first.mesh_vertnum.tolist() == [4]


def test_an_edited_mesh_or_mjcf_compiles_again(robot_dir, tmp_path):
    mjcf = robot_dir / "robot.xml"
    key = model_key(mjcf)
    small = compiled_model(mjcf)
    mesh = robot_dir / "assets" / "box.obj"
    mesh.write_text(BOX.replace("v 0 0 1", "v 0 0 2").replace("v 1 0 0", "v 3 0 0"))
    os.utime(mesh, ns=(2_000_000_000, 2_000_000_000))  # MuJoCo's own mesh cache looks at mtimes
    assert model_key(mjcf) != key
    taller = compiled_model(mjcf)
    np.testing.assert_array_equal(taller.mesh_vert,
                                  mujoco.MjModel.from_xml_path(str(mjcf)).mesh_vert)
    assert not np.array_equal(taller.body_inertia, small.body_inertia)  # a bigger mesh
    mjcf.write_text(MJCF.replace('range="-1 1"', 'range="-2 2"'))
    os.utime(mjcf, ns=(1, 1))
    assert compiled_model(mjcf).jnt_range.tolist() == [[-2.0, 2.0]]
    assert len(list((tmp_path / "cache" / "mujoco").glob("*.mjb"))) == 3


def test_a_broken_mjcf_still_raises_mujocos_error(robot_dir, tmp_path):
    (robot_dir / "robot.xml").write_text("<mujoco><worldbody><body></mujoco>")
    with pytest.raises(ValueError):
        compiled_model(robot_dir / "robot.xml")
    assert not list((tmp_path / "cache").rglob("*.mjb"))


def test_models_come_without_the_viewers_bvh_marks_and_simulate_the_same(robot_dir):
    mjcf = robot_dir / "robot.xml"
    for model in (compiled_model(mjcf), compiled_model(mjcf)):  # built, then from the MJB
        assert model.vis.global_.bvactive == 0
    reference = mujoco.MjModel.from_xml_path(str(mjcf))
    reference.vis.global_.bvactive = 1  # MuJoCo's default, which clears nbvh bytes a step
    ours, theirs = mujoco.MjData(model), mujoco.MjData(reference)
    for d in (ours, theirs):
        d.qvel[0] = 2.0
    for _ in range(200):
        mujoco.mj_step(model, ours)
        mujoco.mj_step(reference, theirs)
    assert abs(ours.qpos[0]) > 0.1  # it moved
    np.testing.assert_allclose(ours.qpos, theirs.qpos, atol=1e-12)
