"""Fingers of one hand collide like any other pair: caught by the verdict, kept apart in the
finger targets and by the repair; the robot YAML may exclude only pairs that touch by construction."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from embody.config import RobotConfig
from embody.errors import ConfigError
from embody.retarget.control import separate
from embody.retarget.finger_clearance import CLEARANCE, FingerClearance, clear_fingers
from embody.retarget.validation import validation_counts
from embody.robot import load_robot, robots_dir
from embody.robot.contacts import contact_pairs, self_collision_contacts

#: Left thumb (thumb_0..2), index (0, 1), middle (0, 1): the thumb tip ~21 mm inside the index
#: finger on the MJCF's collision geometry (found by sampling the hand's joint range).
PINCH = np.array([-0.52, 0.70, 0.64, -1.29, -0.65, -1.16, -1.63])
PAIR = ("left_hand_index_1_link", "left_hand_thumb_2_link")


@pytest.fixture(scope="module")
def robot():
    return load_robot(RobotConfig(name="unitree_g1_dex3"))


def _pose(robot, hand: np.ndarray) -> np.ndarray:
    q = robot.rest.copy()
    q[[robot.joint_index(n) for n in robot.hand_joint_names("left")]] = hand
    return q


def _closest(robot, q: np.ndarray) -> float:
    """Signed distance (m) of the left hand's closest counted pair within 5 cm at q (MuJoCo)."""
    fc = FingerClearance(robot, clearance=0.05)
    dist, _ = fc._contacts(0, q)
    return float(dist.min(initial=np.inf))


def test_thumb_index_penetration_is_caught(robot):
    q = _pose(robot, PINCH)[None]
    assert self_collision_contacts(robot, q)[0] > 0
    assert set(contact_pairs(robot, q)) == {PAIR}
    assert validation_counts(robot, q, 30.0)["self_collision_frames"] == 1.0


def test_finger_targets_stop_where_the_fingers_meet(robot):
    names = robot.hand_joint_names("left") + robot.hand_joint_names("right")
    flat = np.zeros(len(names))
    hand_q = np.stack([np.r_[PINCH, np.zeros(7)], flat])
    out = clear_fingers(robot, hand_q, names)
    q = _pose(robot, out[0, :7])[None]
    assert self_collision_contacts(robot, q)[0] == 0
    d = _closest(robot, q[0])
    assert 0.0 <= d <= CLEARANCE + 1e-3  # met as closely as the hand allows, not pulled far apart
    assert 0.02 < np.abs(out[0, :7] - PINCH).max() < 0.6
    np.testing.assert_allclose(out[1], flat, atol=0)  # a clear hand keeps its targets


def test_a_second_clearance_solves_only_the_frames_that_changed(robot):
    names = robot.hand_joint_names("left") + robot.hand_joint_names("right")
    # a pinch closing over 8 frames: its last frames need the clearance
    hand_q = np.stack([np.r_[PINCH * f, np.zeros(7)] for f in np.linspace(0.3, 1.0, 8)])
    first = clear_fingers(robot, hand_q, names)
    assert np.abs(first - hand_q).max() > 0.02
    changed = first.copy()
    changed[6, :7] = PINCH  # one frame put back into the thumb-through-index pose
    again = clear_fingers(robot, changed, names, cleared=first)
    keep = np.r_[0:6]
    np.testing.assert_allclose(again[keep], first[keep], atol=1e-12)  # frames before it untouched
    q = np.stack([_pose(robot, again[t, :7]) for t in range(len(again))])
    assert (self_collision_contacts(robot, q) == 0).all()  # the changed frame is cleared again
    assert np.abs(again[6, :7] - PINCH).max() > 0.02
    full = clear_fingers(robot, changed, names)  # the same as clearing every frame again
    np.testing.assert_allclose(again[6], full[6], atol=1e-3)


def test_repair_separates_the_fingers(robot):
    q = np.repeat(_pose(robot, PINCH)[None], 12, axis=0)
    fixed = separate(robot, q, 30.0)
    assert (self_collision_contacts(robot, fixed) == 0).all()
    arms = robot.ik_mask
    assert np.abs(fixed[:, ~arms] - q[:, ~arms]).max() > 0.01  # the fingers moved


def _write_robot(tmp_path, name: str, extra: dict) -> RobotConfig:
    """The default G1 with one more excluded pair, as robot `name` (robots load once per name)."""
    spec = yaml.safe_load((robots_dir(RobotConfig()) / "unitree_g1_dex3.yaml").read_text())
    spec["collision"]["ignore_pairs"].append(extra)
    (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(spec))
    return RobotConfig(name=name, robots_dir=str(tmp_path))


def test_exclusion_of_a_pair_not_always_in_contact_is_refused(tmp_path):
    cfg = _write_robot(tmp_path, "always", {"bodies": list(PAIR), "kind": "always", "reason": "thumb meets index"})
    with pytest.raises(ConfigError, match=r"collision\.ignore_pairs\.\d+.*not in contact at every pose") as exc:
        load_robot(cfg)
    assert "\n" not in str(exc.value)


def test_exclusions_inside_a_hand_must_touch_by_construction(tmp_path):
    cfg = _write_robot(tmp_path, "joint", {"bodies": list(PAIR), "kind": "joint", "reason": "x"})
    with pytest.raises(ConfigError, match="not a joint's two links"):
        load_robot(cfg)
    cfg = _write_robot(tmp_path, "structural", {"bodies": list(PAIR), "kind": "structural", "reason": "x"})
    with pytest.raises(ConfigError, match=r"ignore_pairs\.\d+\.kind"):
        load_robot(cfg)


def test_a_pair_in_contact_at_every_pose_is_accepted(tmp_path):
    # the thumb's base sits 20 mm inside the palm's hull whatever the thumb does
    cfg = _write_robot(tmp_path, "base", {"bodies": ["left_wrist_yaw_link", "left_hand_thumb_0_link"],
                                          "kind": "always", "reason": "thumb base in the palm hull"})
    assert load_robot(cfg).name == "base"


def test_an_mjcf_exclude_not_always_in_contact_is_lifted_and_counted():
    # H1's MJCF <exclude>s torso/shoulder-roll, which meet in ~10 % of shoulder poses (up to
    # ~12 mm): unlisted in the YAML, the loader lifts the exclusion and MuJoCo reports the pair
    from embody.robot.exclusions import pair_depths
    h1 = load_robot(RobotConfig(name="unitree_h1"))
    torso, housing = h1.model.body("torso_link").id, h1.model.body("left_shoulder_roll_link").id
    depth = pair_depths(h1.model, torso, housing, h1.spec.collision.geom_groups)
    assert 0.02 < (depth < 0).mean() < 0.3 and -0.02 < depth.min() < -0.005
    q = h1.rest.copy()
    q[h1.joint_index("left_shoulder_pitch")] = -2.4  # arm raised high in front: the housing turns in
    q[h1.joint_index("left_shoulder_roll")] = 0.3
    assert set(contact_pairs(h1, q[None])) == {("left_shoulder_roll_link", "torso_link")}


def _shoulder_in_torso(robot) -> np.ndarray:
    """Left arm raised forward (pitch −1.5) and rolled 0.25 rad inward: the shoulder-roll
    housing (its collision cylinder) inside the torso shell, and nothing else touching."""
    q = robot.rest.copy()
    q[robot.joint_index("left_shoulder_pitch_joint")] = -1.5
    q[robot.joint_index("left_shoulder_roll_joint")] = -0.25
    return q


def test_a_pair_not_always_in_contact_is_refused_as_an_exclusion(tmp_path):
    # the shoulder-roll housing meets the torso in ~38 % of its poses (on the real meshes too)
    cfg = _write_robot(tmp_path, "shoulder", {"bodies": ["torso_link", "left_shoulder_roll_link"],
                                              "kind": "always", "reason": "housing grazes the torso"})
    with pytest.raises(ConfigError, match=r"collision\.ignore_pairs\.\d+'?: torso_link–left_shoulder_roll_link "
                                          r"is not in contact at every pose: clear at \d+ of 300") as exc:
        load_robot(cfg)
    assert "\n" not in str(exc.value)


def test_the_shoulder_housing_in_the_torso_is_caught_and_repaired(robot):
    q = _shoulder_in_torso(robot)[None]
    assert set(contact_pairs(robot, q)) == {("left_shoulder_roll_link", "torso_link")}
    assert validation_counts(robot, q, 30.0)["self_collision_frames"] == 1.0
    fixed = separate(robot, np.repeat(q, 6, axis=0), 30.0)
    assert (self_collision_contacts(robot, fixed) == 0).all()
