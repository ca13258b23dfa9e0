"""The robot contact measure's distance check: known distances between hulls, and G1 hand pairs
that MuJoCo's native CCD reads as 0.0 while they are centimetres apart (mujoco#3383)."""

import mujoco
import numpy as np
import pytest

from embody.metrics.convex_distance import geom_distance, hull_distance

CUBE = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T * 0.05


@pytest.mark.parametrize("shift, expected", [((0.13, 0, 0), 0.03), ((0.12, 0.11, 0), np.hypot(0.02, 0.01)),
                                             ((0.101, 0.02, -0.03), 0.001)])
def test_hull_distance_brackets_known_distances(shift, expected):
    rot = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    lower, upper = hull_distance(CUBE @ rot.T, (CUBE + shift) @ rot.T)
    assert lower <= expected + 1e-9 <= upper + 2e-9 and upper - lower <= 2e-4


def test_overlapping_hulls_touch():
    lower, upper = hull_distance(CUBE, CUBE + [0.09, 0.0, 0.0])
    assert lower == 0.0 and upper < 2e-4


#: A G1 pose of the default run (sequence 0, frame 42, hands before the body): MuJoCo 3.11 reads
#: the left wrist against the right thumb as 0.0 while their hulls are 5.7 cm apart (at these
#: exact values: rounded to 6 decimals MuJoCo reads 5.7 cm, so the bug is brittle).
G1_Q = [
    0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.017918078569763518, -0.003118181070382732,
    0.03518941729975786, -0.08003947439256762, 0.07791901351043118, -0.14786349808283053,
    -0.11706512627027352, 0.5550739970834334, -0.5791863469196714, -0.02736249948942574,
    -0.26142012050382624, 0.3802474480055654, 0.6337445363135539, -0.10465120913982391, -1.5440727335696036,
    -0.1038712808251381, -1.5447474466812152, 0.007367862067637523, -0.07248483120321592,
    0.15511348174657263, 0.011806606641902135, -0.7690477491045532, -0.8615234430132842,
    -0.14369854663924264, -0.26185198549545236, -0.38087561526611247, -0.6347914797482851, 0.104609194034338,
    1.5440124496488998, 0.1044621372640133, 1.543488006213078,
]


def test_geom_distance_replaces_false_zero_on_g1():
    """Wherever MuJoCo says ≤ 0 but the hulls are apart, the checked distance is the hulls'; a
    positive MuJoCo reading stands (and lies within the hull bounds)."""
    from embody.config import Config
    from embody.metrics.convex_distance import geom_points
    from embody.metrics.embodiments import RobotContactGeoms, robot_contacts
    from embody.robot import load_robot

    robot = load_robot(Config().robot)
    m, d = robot.model, mujoco.MjData(robot.model)
    geoms = RobotContactGeoms(robot)
    d.qpos[:] = robot.qpos(np.array(G1_Q))
    mujoco.mj_kinematics(m, d)
    fromto, false_zero = np.zeros(6), 0
    for ga in geoms.sets["left_hand"]:
        for gb in geoms.sets["right_hand"]:
            native = mujoco.mj_geomDistance(m, d, ga, gb, 0.1, fromto)
            ours = geom_distance(m, d, ga, gb, 0.1, fromto)
            lower, upper = hull_distance(geom_points(m, d, ga), geom_points(m, d, gb))
            if native > 0:
                assert ours == native and min(lower, 0.1) - 1e-4 <= native <= upper + 1e-4  # capped at 0.1
            else:
                false_zero += lower > 0.01
                assert lower <= ours <= upper
    if mujoco.__version__.startswith("3.11"):
        assert false_zero >= 1  # the bug this guards against, present in this MuJoCo
    hands = robot_contacts(robot, np.array([G1_Q]))[0, 0]
    assert hands > 0.005  # the nearest pair is 8.8 mm apart, not the false 0.0


def test_robot_contacts_equal_every_pair_measured():
    """The broad phase (bounding spheres) leaves the least distances unchanged, bit for bit:
    per frame and channel the same value as `closest_pair` over all the channel's geom pairs,
    on frames from the T-pose to hands together before the body (near and far pairs both)."""
    from embody.config import Config
    from embody.metrics.embodiments import RobotContactGeoms, closest_pair, robot_contacts
    from embody.metrics.fidelity import CONTACTS
    from embody.robot import load_robot

    robot = load_robot(Config().robot)
    m, d = robot.model, mujoco.MjData(robot.model)
    rng = np.random.default_rng(5)
    s = np.linspace(0.0, 1.0, 12)[:, None]
    q = (1 - s) * robot.tpose + s * np.array(G1_Q)
    q = np.concatenate([q, q[6:] + rng.normal(scale=0.15, size=q[6:].shape)])
    got = robot_contacts(robot, q)
    geoms = RobotContactGeoms(robot)
    expected = np.empty_like(got)
    for t, qt in enumerate(q):
        d.qpos[:] = robot.qpos(qt)
        mujoco.mj_kinematics(m, d)
        for c, name in enumerate(CONTACTS):
            a, b = geoms.pairs[name]
            expected[t, c] = closest_pair(m, d, geoms.sets[a], geoms.sets[b], 0.1)[0]
    assert np.array_equal(got, expected)
    assert (got < 0.1).sum() >= 3 and (got == 0.1).sum() >= 3  # near and far channels both
