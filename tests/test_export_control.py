"""The exported trajectory is the validated one: collision-free at every control sample by
construction, re-validated as written, refused when tampered, readable by its consumers."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import mujoco
import numpy as np
import pandas as pd
import pytest

from embody.cli import main
from embody.config.ik import IKConfig
from embody.export.formats import beyondmimic_columns, read_trajectory
from embody.export.library import Trajectory, check_library, export_library
from embody.retarget.control import control_trajectory
from embody.retarget.ik import solve
from embody.retarget.limits import resample
from embody.retarget.targets import Targets, robot_arm_length
from embody.retarget.validation import validation_counts
from embody.robot import load_robot
from embody.robot.contacts import self_collision_contacts

RATE = 50.0


#: The kinematic validation counters (the contact repair's business).
KINEMATIC = ("joint_limit_violations", "velocity_violations", "self_collision_frames")

@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _pose(robot, z: float) -> np.ndarray:
    """Forearms forward, hands in front of the chest; z lifts the left hand and lowers the right."""
    q = robot.rest.copy()
    for name, v in (("left_shoulder_pitch_joint", -0.6 - z), ("right_shoulder_pitch_joint", -0.6 + z),
                    ("left_elbow_joint", 1.0), ("right_elbow_joint", 1.0),
                    ("left_shoulder_yaw_joint", -0.5), ("right_shoulder_yaw_joint", 0.5)):
        q[robot.joint_index(name)] = v
    return robot.clip(q)


@pytest.fixture(scope="module")
def passing(robot):
    """Two source frames (10 fps) with the hands clear of each other, passing through each other
    in between: the plain 50 Hz resample penetrates."""
    q = np.stack([_pose(robot, -0.2), _pose(robot, 0.2)])
    return q, 10.0


@pytest.fixture(scope="module")
def gentle(robot):
    """Two frames one second apart (1 fps) whose hands stay clear: a motion the motors can drive
    (the export refuses one over the effort limits, as the fast pass above is)."""
    q = np.stack([_pose(robot, -0.4), _pose(robot, -0.3)])
    return q, 1.0


@pytest.fixture(scope="module")
def slow_passing(robot):
    """The pass of `passing` over one second (1 fps): its plain resample penetrates."""
    q = np.stack([_pose(robot, -0.2), _pose(robot, 0.2)])
    return q, 1.0


def _independent_contacts(robot, q: np.ndarray) -> np.ndarray:
    """Penetrating contacts per frame between the two hands (left/right wrist subtrees), straight
    from MuJoCo, without embody's contact filter."""
    m = robot.model
    d = mujoco.MjData(m)
    names = [m.body(b).name for b in m.geom_bodyid]
    side = np.array([int(n.startswith(("left_wrist", "left_hand")))
                     - int(n.startswith(("right_wrist", "right_hand"))) for n in names])
    out = []
    for qt in q:
        d.qpos[:] = robot.qpos(qt)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        g = d.contact.geom[: d.ncon]
        pen = d.contact.dist[: d.ncon] < 0
        out.append(int((pen & (side[g[:, 0]] * side[g[:, 1]] == -1)).sum()))
    return np.array(out)


def test_plain_resample_penetrates_between_clear_source_frames(robot, passing):
    q, fps = passing
    assert self_collision_contacts(robot, q).sum() == 0
    plain = resample(q, fps, RATE)
    assert (self_collision_contacts(robot, plain) > 0).sum() >= 3
    assert (_independent_contacts(robot, plain) > 0).sum() >= 3


def test_control_trajectory_is_collision_free_at_every_sample(robot, passing):
    q, fps = passing
    qc = control_trajectory(robot, q, fps, RATE, limits=None)  # the contact repair alone
    assert qc.shape == resample(q, fps, RATE).shape and qc.dtype == np.float64
    assert self_collision_contacts(robot, qc).tolist() == [0] * len(qc)
    assert _independent_contacts(robot, qc).tolist() == [0] * len(qc)
    counts = validation_counts(robot, qc, RATE)  # torque: tests/test_dynamics_limits.py (this toy
    # moves the arms 0.4 rad in 0.1 s from and to nowhere: no torque-feasible answer near it)
    assert {k: counts[k] for k in KINEMATIC} == {k: 0.0 for k in KINEMATIC}
    # strictly inside the limits, so the float32 cast (BeyondMimic reads float32) stays valid
    q32 = qc.astype(np.float32).astype(np.float64)
    assert validation_counts(robot, q32, RATE)["joint_limit_violations"] == 0
    assert validation_counts(robot, q32, RATE)["velocity_violations"] == 0
    # the repair is local: samples stay near the interpolation (radians)
    assert np.abs(qc - resample(q, fps, RATE)).max() < 0.5


def test_ik_solution_collision_free_at_both_rates_without_proxies(robot):
    """Without the proxy penalty the IK plants the hands inside each other; the MuJoCo repair
    still leaves every written sample (source and control rate) free of penetration."""
    t = 4
    q = np.tile(robot.rest, (t, 1))
    import torch
    with torch.no_grad():
        p, r = robot.link_points(torch.tensor(q), ["left_wrist", "right_wrist", "left_elbow", "right_elbow"])
    eye = np.tile(np.eye(3), (t, 1, 1))
    targets = Targets(wrist_pos=p[:, :2].numpy().copy(), wrist_rot=r[:, :2].numpy(),
                      elbow_pos=p[:, 2:].numpy(), torso_rot=eye, head_rot=eye,
                      hand_q=np.zeros((t, 0)), hand_joints=[], fps=30.0,
                      arm_length=robot_arm_length(robot))
    targets.wrist_pos[:, 0] = [0.30, 0.05, 0.10]
    targets.wrist_pos[:, 1] = [0.30, -0.05, 0.10]
    sol = solve(robot, targets, IKConfig(w_collision=0.0, iterations=10))
    assert self_collision_contacts(robot, sol.q).sum() == 0
    assert self_collision_contacts(robot, sol.q_control).sum() == 0
    assert sol.metrics["self_collision_frames"] == 0


def _trajectory(robot, q: np.ndarray, sid: str = "pass") -> Trajectory:
    zero = {"joint_limit_violations": 0, "velocity_violations": 0, "self_collision_frames": 0,
            "torque_viol": 0}
    return Trajectory(id=sid, robot=robot.name, joint_names=tuple(robot.joint_names), q=q,
                      dt=1.0 / RATE, text="pass", validation=zero)


def test_export_refuses_tampered_trajectory(robot, gentle, slow_passing, tmp_path):
    """Stored counters claim 0, but the array penetrates: the export re-validates and refuses."""
    good = _trajectory(robot, control_trajectory(robot, *gentle, RATE), "good")
    bad = _trajectory(robot, resample(*slow_passing, RATE), "tampered")
    library, excluded = export_library([good, bad], tmp_path, "npz", robot=robot)
    assert library["id"].tolist() == ["good"]
    row = excluded.set_index("id").loc["tampered"]
    assert row["status"] == "refused" and "self_collision_frames=" in row["reason"]
    assert not (tmp_path / "tampered.npz").exists()
    meta = json.loads((tmp_path / "library.json").read_text())
    assert meta["robot"] == robot.name and meta["format"] == "npz"
    assert [e["id"] for e in meta["sequences"]] == ["good"]
    assert meta["sequences"][0]["written"]["self_collision_frames"] == 0


@pytest.mark.parametrize("fmt", ["npz", "csv", "gmr", "beyondmimic"])
def test_check_revalidates_library(robot, gentle, slow_passing, tmp_path, fmt, capsys):
    q, fps = slow_passing
    export_library([_trajectory(robot, control_trajectory(robot, *gentle, RATE))], tmp_path, fmt,
                   robot=robot)
    table = check_library(tmp_path, robot)
    kinematic = table[["joint_limit_violations", "velocity_violations", "self_collision_frames"]].eq(0)
    assert kinematic.all(axis=1).tolist() == [True]
    # a gentle motion the motors drive: physics-valid too
    assert table["physics_valid"].tolist() == [True] and table["ok"].tolist() == [True]
    assert table["torque_over_samples"].iloc[0] == 0
    # a received file edited to penetrate fails the check
    path = tmp_path / pd.read_csv(tmp_path / "library.csv")["file"][0]
    bad = resample(q, fps, RATE)
    if fmt == "npz":
        _trajectory(robot, bad).save(path.with_suffix(""), "npz")
    elif fmt == "gmr":
        motion = pickle.loads(path.read_bytes())
        motion["dof_pos"] = bad
        path.write_bytes(pickle.dumps(motion))
    elif fmt == "csv":
        _trajectory(robot, bad).save(path.with_suffix(""), "csv")
    else:
        rows = np.loadtxt(path, delimiter=",")
        rows[:, 7:] = bad[:, beyondmimic_columns(robot.joint_names)[0]]
        np.savetxt(path, rows, delimiter=",")
    capsys.readouterr()
    assert check_library(tmp_path, robot)["self_collision_frames"].iloc[0] > 0
    assert main(["export", "--check", str(tmp_path)]) == 1
    assert "FAIL pass" in capsys.readouterr().out
    assert main(["export", "--check", str(tmp_path / "nowhere")]) == 2


def test_gmr_pickle_round_trip(robot, passing, tmp_path):
    """Read as GMR's consumers do (pickle.load; qpos = root_pos | root_rot xyzw→wxyz | dof_pos)."""
    q, fps = passing
    qc = control_trajectory(robot, q, fps, RATE)
    path = _trajectory(robot, qc).save(tmp_path / "m", "gmr", robot)
    assert path.suffix == ".pkl"
    with open(path, "rb") as f:
        motion = pickle.load(f)
    assert set(motion) == {"fps", "root_pos", "root_rot", "dof_pos", "local_body_pos", "link_body_list"}
    assert motion["fps"] == 50 and motion["local_body_pos"] is None
    t = len(qc)
    assert motion["root_pos"].shape == (t, 3) and motion["root_rot"].shape == (t, 4)
    assert motion["dof_pos"].shape == (t, robot.model.nq - 7) and motion["dof_pos"].dtype == np.float64
    m = robot.model
    for k in (0, t // 2, t - 1):
        qpos = np.concatenate([motion["root_pos"][k], motion["root_rot"][k][[3, 0, 1, 2]],
                               motion["dof_pos"][k]])
        np.testing.assert_array_equal(qpos, robot.qpos(qc[k]))  # MJCF qpos order, fingers included
    np.testing.assert_allclose(np.linalg.norm(motion["root_rot"], axis=1), 1.0)
    assert m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE


def test_beyondmimic_csv_round_trip(robot, passing, tmp_path):
    """Read as BeyondMimic's csv_to_npz does: loadtxt(delimiter=","), float32, base pos 0:3,
    base quat xyzw 3:7 (→ wxyz by [3, 0, 1, 2]), joint positions 7:."""
    q, fps = passing
    qc = control_trajectory(robot, q, fps, RATE)
    path = _trajectory(robot, qc).save(tmp_path / "m", "beyondmimic", robot)
    motion = np.loadtxt(path, delimiter=",").astype(np.float32)
    body, fingers = beyondmimic_columns(robot.joint_names)
    assert motion.shape == (len(qc), 7 + 29) and len(fingers) == 14
    base_pos, base_rot = motion[:, :3], motion[:, 3:7][:, [3, 0, 1, 2]]
    np.testing.assert_allclose(base_pos, np.tile(robot.model.qpos0[:3], (len(qc), 1)), atol=1e-6)
    np.testing.assert_allclose(base_rot, np.tile(robot.model.qpos0[3:7], (len(qc), 1)), atol=1e-6)
    np.testing.assert_allclose(motion[:, 7:], qc[:, body], atol=1e-6)
    extra = pd.read_csv(tmp_path / "m.extra_joints.csv")
    assert list(extra.columns) == [robot.joint_names[i] for i in fingers]
    np.testing.assert_allclose(extra.to_numpy(), qc[:, fingers], atol=1e-12)
    read = read_trajectory(path, "beyondmimic", robot.joint_names, max_frames=10_000).q
    np.testing.assert_allclose(read, qc, atol=1e-6)
    assert validation_counts(robot, read, RATE)["joint_limit_violations"] == 0


def test_proxies_cover_fingers_against_other_palm_and_thighs(robot):
    """Every finger link of each hand carries proxy points paired with the other hand's palm hull
    and with every thigh hull (the differentiable penalty sees these contacts)."""
    from embody.robot.proxies import robot_proxies

    p = robot_proxies(robot)
    pairs = {(p.bodies[p.sphere_body[s]], p.bodies[p.hull_body[h]]) for s, h in p.hull_pairs}
    thighs = {b for b in p.bodies if "_hip_" in b}
    assert thighs
    for side, other in (("left", "right"), ("right", "left")):
        fingers = [b for b in p.bodies if b.startswith(f"{side}_hand_")]
        assert len(fingers) == 7
        for f in fingers:
            assert (f, f"{other}_wrist_yaw_link") in pairs, f  # the palm
            for t in thighs:
                assert (f, t) in pairs, (f, t)


def test_bridge_replaces_a_short_contact_run_between_clear_frames(robot, passing):
    """Hands passing through each other on one frame between clear ones: `bridge_contacts`
    replaces that frame by a clear one next to it and touches nothing else; a run longer than
    `max_run` is left to the repair."""
    from embody.retarget.control import bridge_contacts

    q = np.stack([_pose(robot, z) for z in (-0.4, -0.2, 0.0, 0.2, 0.4)])
    bad = self_collision_contacts(robot, q) > 0
    assert bad.tolist() == [False, False, True, False, False]
    out = bridge_contacts(robot, q)
    assert self_collision_contacts(robot, out).sum() == 0
    np.testing.assert_array_equal(out[~bad], q[~bad])
    assert np.abs(out[2] - q[2]).max() <= np.abs(q[3] - q[1]).max()  # a local answer, not a jump
    np.testing.assert_array_equal(bridge_contacts(robot, q, max_run=0), q)


def test_bridge_verdict_is_mujocos_and_spares_the_repair_a_second_check(robot, passing):
    """`bridge_contacts_checked` hands on MuJoCo's verdict on what it returns (bridged samples
    clear, an unbridged run still touching); `separate_checked` given it returns exactly what it
    returns checking every sample itself, and asks MuJoCo only about the touching ones."""
    from embody.retarget import control

    q = np.stack([_pose(robot, z) for z in (-0.4, -0.2, 0.0, 0.2, 0.4)])
    out, verdict = control.bridge_contacts_checked(robot, q)
    np.testing.assert_array_equal(verdict, self_collision_contacts(robot, out) > 0)
    assert not verdict.any()
    kept, verdict = control.bridge_contacts_checked(robot, q, max_run=0)
    np.testing.assert_array_equal(kept, q)
    assert verdict.tolist() == [False, False, True, False, False]
    plain = resample(*passing, RATE)
    _, touching = control.bridge_contacts_checked(robot, plain, max_run=0)
    assert touching.sum() >= 3
    asked: list[int] = []
    original = control._Separator.contacts

    def counted(self, x, jacobians=True):
        asked.append(1)
        return original(self, x, jacobians)

    full, full_clear = control.separate_checked(robot, plain, RATE)
    control._Separator.contacts = counted
    try:
        given, given_clear = control.separate_checked(robot, plain, RATE, touching=touching)
        first = len(asked)
        asked.clear()
        control.separate_checked(robot, plain, RATE)
    finally:
        control._Separator.contacts = original
    np.testing.assert_array_equal(given, full)
    assert given_clear == full_clear and given_clear
    assert len(asked) - first == len(plain) - int(touching.sum())  # the clear samples, asked once less


def test_export_repair_is_local_where_the_bridge_fails(robot):
    """Hands passing through each other between two clear 10 fps frames: four 50 Hz samples
    touch, and the straight (= resampled), pushed and held bridges between their clear
    neighbours all touch or break the velocity limits. The export still clears every sample,
    and locally: no joint moves more than 10° (the export tries 5°, 7.5° and 10° trust boxes
    before anything wider; the unbounded push moved it 21°, and 110° on synth seq 17), and no
    sample further than 6 from one closer than the export's gap moves (the hat's half width is
    max(0.1 s × 50 Hz, 2 × 10° / (5 rad/s / 50 Hz)) = 5 samples, plus one for the clamp)."""
    from embody.retarget.control import BOX_MARGIN, BRIDGE_FRAMES, bridge_contacts, control_trajectory_checked
    from embody.retarget.limits import clamp_velocity

    fps = 10.0
    q = np.stack([_pose(robot, z) for z in (-0.4, -0.4, -0.4, -0.2, 0.2, 0.4, 0.4, 0.4)])
    assert self_collision_contacts(robot, q).sum() == 0
    plain = clamp_velocity(np.clip(resample(q, fps, RATE), robot.lower + BOX_MARGIN, robot.upper - BOX_MARGIN),
                           robot.velocity_limits * (1 - 1e-5), RATE)
    bad = np.flatnonzero(self_collision_contacts(robot, plain) > 0)
    assert len(bad) >= 3 and np.all(np.diff(bad) == 1)  # one run
    run = int(np.ceil(BRIDGE_FRAMES * RATE / fps))
    np.testing.assert_array_equal(bridge_contacts(robot, plain, max_run=run, fps=RATE), plain)  # no bridge
    qc, clear, _ = control_trajectory_checked(robot, q, fps, RATE, limits=None)  # the contact repair alone
    assert clear
    assert self_collision_contacts(robot, qc).sum() == 0 and _independent_contacts(robot, qc).sum() == 0
    assert all(validation_counts(robot, qc, RATE)[k] == 0 for k in KINEMATIC)
    drift = np.degrees(np.abs(qc - plain).max(axis=1))
    assert drift.max() <= 10.0 + 1e-9
    moved = np.flatnonzero(drift > 1e-9)
    # every moved sample is near one the repair had to act on: touching, or (the export's gap)
    # with a counted pair closer than EXPORT_GAP
    from embody.retarget.limits import EXPORT_GAP
    from embody.robot.contacts import near_contacts
    near = np.flatnonzero(near_contacts(robot, plain, EXPORT_GAP) > 0)
    assert set(bad) <= set(near)
    assert (np.abs(moved[:, None] - near[None, :]).min(1) <= 6).all()


def test_separate_stays_inside_its_trust_radius(robot, passing):
    """`separate` with one trust radius never moves a joint further than that from its input,
    and reports not clear rather than leave it; the default ladder ends unbounded and clears."""
    from embody.retarget.control import separate_checked

    q, fps = passing
    plain = resample(q, fps, RATE)
    for radius in (0.5, 5.0):
        out, clear = separate_checked(robot, plain, RATE, trust_deg=(radius,))
        assert np.degrees(np.abs(out - plain).max()) <= radius + 1e-9
        if clear:
            assert self_collision_contacts(robot, out).sum() == 0
    out, clear = separate_checked(robot, plain, RATE, trust_deg=(0.5,))
    assert not clear  # 0.5° cannot separate hands passing through each other
    out, clear = separate_checked(robot, plain, RATE)
    assert clear and self_collision_contacts(robot, out).sum() == 0


def test_a_stalled_trust_radius_is_given_up(robot, passing, monkeypatch):
    """A trust radius that cannot clear the samples (0.5° for hands passing through each other)
    is given up once its fewest-touching count has not improved for `STALL_PASSES` passes,
    whatever the pass budget, and the ladder's next radius clears them; the last radius, whose
    result stands when none clears, runs its whole budget."""
    from embody.retarget import control

    q, fps = passing
    plain = resample(q, fps, RATE)
    passes = []
    spread = control._spread

    def counted(delta, half_width):  # one call per pass that goes on to push
        passes.append(1)
        return spread(delta, half_width)
    monkeypatch.setattr(control, "_spread", counted)
    budget = 10 * control.PASSES
    out, clear = control.separate_checked(robot, plain, RATE, trust_deg=(0.5, None), passes=budget)
    assert clear and self_collision_contacts(robot, out).sum() == 0
    assert control.STALL_PASSES <= len(passes) < 2 * control.STALL_PASSES
    passes.clear()
    out, clear = control.separate_checked(robot, plain, RATE, trust_deg=(0.5,), passes=2 * control.STALL_PASSES)
    assert not clear and len(passes) == 2 * control.STALL_PASSES
    assert np.degrees(np.abs(out - plain).max()) <= 0.5 + 1e-9


def test_repair_clears_a_sample_on_a_run_at_the_velocity_limit(robot):
    """21 samples of a real 50 Hz export (the default run's synth seq 15 after the s11 merges,
    `tests/data`): the wrists move at their velocity limit through sample 10, where the two
    wrist yaw links touch (0.9 mm). A hat there changes the run's slope and the velocity clamp
    undoes it, every pass (the repair before this fix returned not clear, export-invalid);
    the sample is cleared inside its neighbours' reach instead, and only it moves."""
    from embody.retarget.control import BOX_MARGIN, VELOCITY_MARGIN, separate_checked

    data = np.load(Path(__file__).parent / "data" / "g1_wrists_at_velocity_limit_50hz.npz")
    assert list(data["joint_names"]) == list(robot.joint_names)
    q, rate = data["q"], float(data["rate"])
    assert np.flatnonzero(self_collision_contacts(robot, q)).tolist() == [10]
    step = np.abs(np.diff(q, axis=0)) / (robot.velocity_limits / rate)
    assert step[9:11].max() > 0.999                                 # saturated into and out of 10
    out, clear = separate_checked(robot, q, rate, box_margin=BOX_MARGIN, velocity_margin=VELOCITY_MARGIN)
    assert clear
    assert all(validation_counts(robot, out, rate)[k] == 0 for k in KINEMATIC)
    moved = np.flatnonzero(np.abs(out - q).max(axis=1) > 0)
    assert moved.tolist() == [10]
    assert np.degrees(np.abs(out - q).max()) < 5.0


def test_the_export_keeps_counted_pairs_a_tracking_error_apart(robot):
    """A thumb 1.1 mm from the index finger penetrates nothing, but the replay at the real gains
    closes such gaps by up to ~1.9 mm: the exported array pushes it past `EXPORT_GAP`, moving
    only that hand's fingers, and a little."""
    from embody.retarget.limits import EXPORT_GAP
    from embody.robot.contacts import near_contacts
    pose = robot.tpose.copy()
    for name, value in {"right_hand_thumb_0_joint": -1.022, "right_hand_thumb_1_joint": -0.192,
                        "right_hand_thumb_2_joint": -1.426, "right_hand_middle_0_joint": 1.526,
                        "right_hand_middle_1_joint": 1.567, "right_hand_index_0_joint": 1.509,
                        "right_hand_index_1_joint": 0.518}.items():  # index tip 1.1 mm off the thumb
        pose[robot.joint_index(name)] = value
    q = np.repeat(pose[None], 31, axis=0)
    assert (self_collision_contacts(robot, q) == 0).all() and (near_contacts(robot, q, EXPORT_GAP) > 0).all()
    out = control_trajectory(robot, q, 30.0, RATE, limits=None)
    assert (near_contacts(robot, out, EXPORT_GAP) == 0).all()
    moved = np.abs(out - resample(q, 30.0, RATE)).max(0)
    hand = [robot.joint_index(n) for n in robot.hand_joint_names("right")]
    assert np.delete(moved, hand).max() <= 1.01e-6  # only its fingers move (the rest: the box margin)
    assert 0 < moved.max() < np.radians(5.0)
