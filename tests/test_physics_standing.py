"""The G1 standing replay and the simulated self-contacts, on planted motions.

A robot standing still, or moving its arms slowly (ZMP well inside the feet), must stay up; a
motion whose ZMP leaves the feet far must be reported as falling. Self-contacts in simulation are
counted by the kinematic check's own rule (pairs, documented exclusions, depth)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from embody.physics import commands, replay_fixed, replay_standing
from embody.physics.evaluate import sim_contacts, standing_bounds, standing_metrics
from embody.robot import load_robot
from embody.robot.contacts import contact_pairs, self_collision_contacts
from embody.robot.dynamics import GRAVITY, stance_pose, zmp

FPS = 50.0


@pytest.fixture(scope="module")
def g1():
    return load_robot()


def _rest(robot) -> np.ndarray:
    """The stance with the arms hanging (every non-leg joint at 0)."""
    q = stance_pose(robot)
    q[[not n.endswith(("hip_pitch_joint", "hip_roll_joint", "hip_yaw_joint", "knee_joint",
                        "ankle_pitch_joint", "ankle_roll_joint")) for n in robot.joint_names]] = 0.0
    return q


def _arms(robot, q: np.ndarray, pitch: np.ndarray, elbow: np.ndarray) -> np.ndarray:
    """q repeated over len(pitch) samples with both shoulder pitches and elbows set."""
    out = np.repeat(q[None], len(pitch), axis=0)
    for side in ("left", "right"):
        out[:, robot.joint_index(f"{side}_shoulder_pitch_joint")] = pitch
        out[:, robot.joint_index(f"{side}_elbow_joint")] = elbow
    return out


def _stand(robot, q: np.ndarray):
    s = replay_standing(robot, commands(robot, q, FPS))
    return s, standing_metrics(robot, s)


def test_standing_bounds_follow_from_the_zmp_margin(g1):
    b = standing_bounds(g1)
    assert b.com_offset == pytest.approx(0.020) and b.foot_slip == pytest.approx(0.020)
    assert 0.4 < b.com_height < 0.8  # the G1's CoM above its feet
    assert b.tilt == pytest.approx(0.020 / b.com_height)
    assert 0.002 < b.foot_lift < 0.01  # a ~17 cm foot tilted by that angle


def test_g1_standing_still_holds_and_the_feet_carry_the_weight(g1):
    q = np.repeat(_rest(g1)[None], int(3 * FPS) + 1, axis=0)
    s, m = _stand(g1, q)
    assert m["standing_holds"]
    assert m["standing_pelvis_tilt_max_deg"] < 0.5 and m["standing_com_offset_max_mm"] < 5.0
    assert m["standing_foot_slip_max_mm"] < 2.0 and m["standing_foot_lift_max_mm"] < 1.0
    # the floor carries the whole robot (fingers welded in the standing model: the same mass)
    weight = g1.model.body_subtreemass[g1.model.body(g1.spec.root_body).id] * GRAVITY
    np.testing.assert_allclose(s.support.force[:, 2], weight, rtol=1e-3)
    assert m["zmp_multibody_margin_min_mm"] > 20.0 and m["floor_yaw_moment_max_nm"] < 0.1


def test_g1_slow_arm_motion_holds(g1):
    # both arms raised forward 1 rad, elbows bent 0.8 rad, over 4 s: the ZMP stays well inside
    t = np.arange(int(4 * FPS) + 1) / FPS
    ramp = 0.5 * (1 - np.cos(np.pi * t / t[-1]))
    q = _arms(g1, _rest(g1), -1.0 * ramp, 0.8 * ramp)
    _, _, margin = zmp(g1, q, 1 / FPS)
    assert margin.min() > 0.04
    _, m = _stand(g1, q)
    assert m["zmp_multibody_margin_min_mm"] > 40.0
    assert m["standing_holds"]
    assert m["standing_com_offset_max_mm"] < 5.0 and m["standing_pelvis_tilt_max_deg"] < 0.5
    assert m["standing_foot_lift_max_mm"] < 0.5 and m["standing_foot_slip_max_mm"] < 2.0


def test_g1_arm_swing_with_the_zmp_inside_holds(g1):
    # both arms swung together 0.8 rad at 0.5 Hz for 6 s: the ZMP stays ≥ 35 mm inside the feet.
    # The legs' feed-forward follows the moving body; held at its value at rest instead, the
    # stiff-legged robot leans on the PD error until it tips over.
    t = np.arange(int(6 * FPS) + 1) / FPS
    q = _arms(g1, _rest(g1), -0.6 + 0.8 * np.sin(2 * np.pi * 0.5 * t), np.full_like(t, 0.6))
    _, _, margin = zmp(g1, q, 1 / FPS)
    assert margin.min() > 0.035
    s, m = _stand(g1, q)
    assert m["zmp_multibody_margin_min_mm"] > 30.0
    assert m["standing_holds"]
    assert m["standing_pelvis_tilt_max_deg"] < 1.0 and m["standing_com_offset_max_mm"] < 10.0
    legs = np.flatnonzero([n.endswith("ankle_pitch_joint") for n in (g1.joint_names[j] for j in s.rollout.joints)])
    assert np.ptp(s.support.torque[:, legs], axis=0).min() > 1.0  # N·m: the ankles' feed-forward moves


def test_g1_toppling_motion_is_reported_as_falling(g1):
    # both arms whipped forward through 1.4 rad at 2.5 Hz: the ZMP leaves the feet by ~0.5 m
    t = np.arange(int(2 * FPS) + 1) / FPS
    q = _arms(g1, _rest(g1), -1.4 * np.abs(np.sin(2 * np.pi * 1.25 * t)), np.zeros_like(t))
    _, _, margin = zmp(g1, q, 1 / FPS)
    assert margin.min() < -0.3
    _, m = _stand(g1, q)
    assert m["zmp_multibody_margin_min_mm"] < -300.0
    assert not m["standing_holds"]
    assert m["standing_pelvis_tilt_max_deg"] > 45.0 and m["standing_foot_lift_max_mm"] > 50.0


# Planted poses (found by seeded sampling of the joints' ranges): the right thumb's tip link in
# its index finger's, and the left shoulder-roll housing 6 mm into the torso shell (a counted
# pair: it touches in 37-39 % of shoulder poses, so no exclusion).
THUMB_IN_INDEX = {"right_hand_thumb_0_joint": -1.022, "right_hand_thumb_1_joint": -0.192,
                  "right_hand_thumb_2_joint": -1.426, "right_hand_middle_0_joint": 1.526,
                  "right_hand_middle_1_joint": 1.567, "right_hand_index_0_joint": 1.509,
                  "right_hand_index_1_joint": 1.054}
SHOULDER_IN_TORSO = {"left_shoulder_pitch_joint": -2.341, "left_shoulder_roll_joint": -0.183,
                     "left_shoulder_yaw_joint": -0.624}


def _planted(robot, joints: dict[str, float], seconds: float = 1.0) -> np.ndarray:
    q = robot.tpose.copy()
    for name, value in joints.items():
        q[robot.joint_index(name)] = value
    return np.repeat(q[None], int(seconds * FPS) + 1, axis=0)


def test_sim_contacts_follow_the_kinematic_check_on_planted_poses(g1):
    q = _planted(g1, THUMB_IN_INDEX)
    kinematic = self_collision_contacts(g1, q)
    assert (kinematic > 0).all()
    fixed = replay_fixed(g1, commands(g1, q, FPS))
    assert np.abs(fixed.q50 - q).max() < np.deg2rad(1.0)  # a held pose is held
    figures, pairs = sim_contacts(g1, fixed.q50)
    assert figures["sim_contact_samples"] == int((kinematic > 0).sum()) == len(q)
    assert pairs == contact_pairs(g1, q)
    assert pairs[("right_hand_index_1_link", "right_hand_thumb_2_link")] == len(q)
    assert figures["sim_contact_pairs.same_hand"] == sum(pairs.values())
    assert figures["sim_contact_pairs.two_hands"] == figures["sim_contact_pairs.hand_body"] == 0
    # the shoulder housing inside the torso is a counted pair (no exclusion): counted in both
    q = _planted(g1, SHOULDER_IN_TORSO)
    assert (self_collision_contacts(g1, q) > 0).all()
    fixed = replay_fixed(g1, commands(g1, q, FPS))
    figures, pairs = sim_contacts(g1, fixed.q50)
    assert figures["sim_contact_samples"] == len(q)
    assert set(pairs) == set(contact_pairs(g1, q))
    assert any("torso" in a + b and "shoulder_roll" in a + b for a, b in pairs)


def test_the_standing_model_collides_only_feet_and_floor(g1):
    from embody.physics.replay import standing_model
    rm, _, feet = standing_model(g1)
    m = rm.model
    floor = m.geom("physics_floor").id
    colliding = np.flatnonzero(m.geom_contype | m.geom_conaffinity)
    assert sorted(colliding.tolist()) == sorted([*feet.tolist(), floor])
    # the broad phase's per-body masks agree: only the feet's bodies and the world (the floor)
    bodies = np.flatnonzero(m.body_contype | m.body_conaffinity)
    assert sorted(bodies.tolist()) == sorted({0, *m.geom_bodyid[feet].tolist()})
    assert len(bodies) == 3  # world and two feet


def test_the_replay_models_drop_geoms_but_keep_the_robots_dynamics(g1):
    """The fixed-base model keeps no geom and the standing one only the feet and the floor, yet
    both move like the robot's own model: the same joint-space inertia and bias forces (gravity,
    Coriolis) on their joints, against plain MuJoCo on the robot's MJCF."""
    from embody.physics.replay import fixed_model, standing_model
    fixed = fixed_model(g1)
    standing, qpos0, feet = standing_model(g1)
    assert fixed.model.ngeom == 0
    assert standing.model.ngeom == len(feet) + 1  # and the floor
    rng = np.random.default_rng(3)
    full = g1.model
    data = mujoco.MjData(full)
    for rm, legs in ((fixed, np.zeros(g1.n_joints)), (standing, stance_pose(g1))):
        m = rm.model
        d = mujoco.MjData(m)
        d.qpos[:] = m.qpos0 if rm is fixed else qpos0
        q = legs.copy()
        q[rm.joints] = rng.uniform(-0.3, 0.3, len(rm.joints))
        stance = rm.joints[np.isin(rm.joints, np.flatnonzero(legs))]
        q[stance] = legs[stance]
        qd = rng.normal(0.0, 0.5, len(rm.joints))
        d.qpos[rm.qpos_adr] = q[rm.joints]
        d.qvel[rm.dof_adr] = qd
        dof_full = np.array([full.jnt_dofadr[full.joint(g1.joint_names[j]).id] for j in rm.joints])
        data.qpos[:] = full.qpos0
        data.qpos[g1.qpos_adr] = q
        if rm is standing:  # the same base pose
            data.qpos[:7] = d.qpos[:7]
        data.qvel[:] = 0.0
        data.qvel[dof_full] = qd
        for mm, dd in ((m, d), (full, data)):
            mujoco.mj_forward(mm, dd)
        np.testing.assert_allclose(_mass(m, d)[np.ix_(rm.dof_adr, rm.dof_adr)],
                                   _mass(full, data)[np.ix_(dof_full, dof_full)], atol=1e-9)
        np.testing.assert_allclose(d.qfrc_bias[rm.dof_adr], data.qfrc_bias[dof_full], atol=1e-7)


def _mass(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """The joint-space inertia matrix (nv,nv) at d's configuration (columns by `mj_mulM`)."""
    out, column, unit = np.zeros((m.nv, m.nv)), np.zeros(m.nv), np.zeros(m.nv)
    for k in range(m.nv):
        unit[:] = 0.0
        unit[k] = 1.0
        mujoco.mj_mulM(m, d, column, unit)
        out[:, k] = column
    return out
