"""MuJoCo's self-collision verdict on the narrowed collision model (`contacts.collision_model`)."""

import mujoco
import numpy as np
import pytest

from embody.robot import load_robot
from embody.robot.contacts import collision_model, counted_geom_pairs, single_contact


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _counted_contacts(model, counted, robot, q):
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    out = []
    for qt in q:
        data.qpos[robot.qpos_adr] = qt
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        n = data.ncon
        geom, dist = data.contact.geom[:n], data.contact.dist[:n]
        keep = counted[geom[:, 0], geom[:, 1]] & (dist < 0.0)
        out.append(sorted((int(a), int(b), round(float(d), 12)) for (a, b), d in zip(geom[keep], dist[keep])))
    return out


def test_narrowed_model_gives_the_full_models_counted_contacts(robot):
    rng = np.random.default_rng(3)
    ik = np.flatnonzero(robot.ik_mask)
    q = np.tile(robot.rest, (150, 1))
    q[:, ik] = rng.uniform(robot.lower[ik], robot.upper[ik], size=(150, len(ik)))
    # the full model with the verdict's one contact per pair: the narrowing changes nothing else
    full = _counted_contacts(single_contact(robot.model.__copy__()), counted_geom_pairs(robot), robot, q)
    model, counted = collision_model(robot)
    narrow = _counted_contacts(model, counted, robot, q)
    assert sum(map(len, full)) > 100  # random arm poses collide a lot
    assert narrow == full
    assert collision_model(robot) is collision_model(robot)  # cached on the robot


def test_verdict_reports_one_contact_per_pair_at_the_pairs_deepest(robot):
    """The verdict's model gives each touching geom pair one contact (MuJoCo's multi-point mesh
    contacts, several per pair and on mujoco 4.0 at other depths, would make counts and distances
    depend on the version), at the pair's deepest distance to within 0.5 mm of the full model's
    points, and the same pairs touch."""
    rng = np.random.default_rng(5)
    ik = np.flatnonzero(robot.ik_mask)
    q = np.tile(robot.rest, (100, 1))
    q[:, ik] = rng.uniform(robot.lower[ik], robot.upper[ik], size=(100, len(ik)))
    model, counted = collision_model(robot)
    one = _counted_contacts(model, counted, robot, q)
    several = _counted_contacts(robot.model, counted_geom_pairs(robot), robot, q)
    assert sum(map(len, several)) > sum(map(len, one)) > 100  # the default gives some pairs several points
    for mine, theirs in zip(one, several):
        pairs = [(a, b) for a, b, _ in mine]
        assert len(pairs) == len(set(pairs))
        deepest: dict = {}
        for a, b, d in theirs:
            deepest[(a, b)] = min(d, deepest.get((a, b), 0.0))
        assert set(pairs) == set(deepest)
        assert all(abs(d - deepest[(a, b)]) < 5e-4 for a, b, d in mine)


def test_movable_only_keeps_pairs_the_ik_moves(robot):
    _, every = collision_model(robot)
    _, movable = collision_model(robot, 0.002, movable_only=True)
    assert movable.sum() < every.sum() and not (movable & ~every).any()
    left = robot.model.body("left_hand_index_1_link").id
    torso = robot.model.body("torso_link").id
    pelvis = robot.model.body("pelvis").id
    geoms = lambda b: np.flatnonzero(robot.model.geom_bodyid == b)  # noqa: E731
    assert movable[np.ix_(geoms(left), geoms(torso))].any()  # an arm moves the hand off the torso
    legs = [robot.model.body(n).id for n in ("left_knee_link", "right_knee_link")]
    assert not movable[np.ix_(geoms(legs[0]), geoms(legs[1]))].any()  # legs are pinned
    assert not movable[np.ix_(geoms(pelvis), geoms(legs[0]))].any()


def test_collision_bitmasks_pass_exactly_the_counted_pairs(robot):
    """`pair_bits`: MuJoCo's contype/conaffinity filter of the narrowed models lets through the
    counted pairs and no other (G1's legs among themselves, counted by no IK-movable pair, no
    longer reach the exact-contact model's narrow phase), and a relation that is not one
    between bodies gets no bits."""
    from embody.robot.contacts import pair_bits

    for movable_only in (False, True):
        model, counted = collision_model(robot, 0.002, movable_only=movable_only)
        ct, ca = model.geom_contype.astype(np.int64), model.geom_conaffinity.astype(np.int64)
        passes = ((ct[:, None] & ca[None]) | (ca[:, None] & ct[None])) != 0
        b, parent = model.geom_bodyid, model.body_parentid
        passes &= b[:, None] != b[None]  # MuJoCo skips one body's geoms,
        passes &= (parent[b][:, None] != b[None]) & (parent[b][None] != b[:, None])  # and a parent's with its child's
        assert np.array_equal(passes, counted)
    body = np.array([0, 0, 1, 2])
    pairs = np.zeros((4, 4), bool)
    pairs[0, 2] = pairs[2, 0] = True  # body 0's geom 0 pairs with body 1, its geom 1 with body 2
    pairs[1, 3] = pairs[3, 1] = True
    assert pair_bits(body, pairs) is None
