"""Dex3 finger retargeting on the synthetic lexicon's handshapes (fist, flat, pinch, point, C, Y)
given with absolute and with relative (mean-offset) hands: the thumb carries information."""

import numpy as np
import pytest

from embody.io.hands import absolute_to_relative, relative_to_absolute
from embody.retarget.hands import OPPOSE_RANGE, fold_thumbs, palm_rest_weight, rate_limit, retarget_hands
from embody.robot import load_robot
from embody.synth.handshapes import handshape

SHAPES = ("fist", "flat", "pinch", "point", "c", "y", "relaxed")


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _pose(shape: str) -> np.ndarray:
    pose = np.zeros((1, 55, 3))
    pose[0, 25:40], pose[0, 40:55] = handshape(shape, "left"), handshape(shape, "right")
    return pose


def _fractions(robot, q, names, side):
    """How far each robot finger is from open (0) to its limit (1); thumb_0 = opposition."""
    def frac(joint):
        j = robot.joint_index(joint)
        v = q[0, names.index(joint)]
        limit = robot.upper[j] if v >= 0 else robot.lower[j]
        return abs(v / limit) / (OPPOSE_RANGE if "thumb_0" in joint else 1.0) if limit else 0.0
    return {"index": np.mean([frac(f"{side}_hand_index_{k}_joint") for k in (0, 1)]),
            "middle": np.mean([frac(f"{side}_hand_middle_{k}_joint") for k in (0, 1)]),
            "thumb": np.mean([frac(f"{side}_hand_thumb_{k}_joint") for k in (1, 2)]),
            "opposition": frac(f"{side}_hand_thumb_0_joint")}


@pytest.mark.parametrize("convention", ["absolute", "relative"])
@pytest.mark.parametrize("side", ["left", "right"])
def test_handshapes_in_both_conventions(robot, side, convention):
    out = {}
    for shape in SHAPES:
        pose = _pose(shape)
        if convention == "relative":  # what a SOKE/SignAvatars file holds, converted on load
            relative = absolute_to_relative(pose)
            assert not np.allclose(relative, pose)  # the file's numbers really differ
            pose = relative_to_absolute(relative).astype(np.float64)
        q, names = retarget_hands(pose, robot)
        cols = [robot.joint_index(n) for n in names]
        assert q.shape == (1, 14) and np.all(q >= robot.lower[cols]) and np.all(q <= robot.upper[cols])
        out[shape] = _fractions(robot, q, names, side)
    assert all(out["fist"][f] > 0.8 for f in ("index", "middle")) and out["fist"]["opposition"] > 0.9
    assert all(v < 0.15 for v in out["flat"].values())
    assert out["point"]["index"] < 0.05 and out["point"]["middle"] > 0.8
    assert 0.3 < out["pinch"]["index"] < 0.8 and out["pinch"]["opposition"] > 0.6
    assert 0.3 < out["c"]["index"] < 0.8 and 0.2 < out["c"]["thumb"] < 0.8
    assert out["y"]["thumb"] < 0.05 and out["y"]["opposition"] < 0.05 and out["y"]["index"] > 0.8
    # the thumb is not saturated for a relaxed hand, and opposition is driven, in order
    assert 0.2 < out["relaxed"]["thumb"] < 0.8 and 0.2 < out["relaxed"]["opposition"] < 0.9
    order = [out[s]["opposition"] for s in ("y", "flat", "c", "pinch", "fist")]
    assert order == sorted(order) and len(set(np.round(order, 3))) == 5


def test_opposition_brings_the_thumb_to_the_fingers(robot):
    """On the robot's own landmarks: a pinch brings thumb and index tips together; a Y keeps them apart."""
    gaps = {}
    for shape in ("y", "pinch"):
        q_hand, names = retarget_hands(_pose(shape), robot)
        q = robot.tpose.copy()
        q[[robot.joint_index(n) for n in names]] = q_hand[0]
        p, _, _ = robot.landmark_points(q[None], ["right_thumb_tip", "right_index_tip"])
        gaps[shape] = np.linalg.norm(p[0, 0] - p[0, 1])
    assert gaps["pinch"] < gaps["y"] - 0.02


def _thumb_protrusion_mm(robot, q_full) -> float:
    """How far the right Dex3 thumb's collision meshes stand out of the palm face (along the palm
    normal, from the palm landmark), in mm."""
    import mujoco
    m, d = robot.model, mujoco.MjData(robot.model)
    d.qpos[:] = robot.qpos(q_full)
    mujoco.mj_kinematics(m, d)
    pts, nrm, names = robot.landmark_points(q_full[None])
    world = robot.torso_from_world
    p, n = pts[0, names.index("right_palm")], nrm[0, 1]
    groups = list(robot.spec.collision.geom_groups)
    out = []
    for g in range(m.ngeom):
        if m.geom_group[g] not in groups or not m.body(m.geom_bodyid[g]).name.startswith("right_hand_thumb"):
            continue
        mid = m.geom_dataid[g]
        v = m.mesh_vert[m.mesh_vertadr[mid]: m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
        v = v @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
        out.append((((v @ world[:3, :3].T + world[:3, 3]) - p) @ n).max())
    return 1000.0 * float(max(out))


def test_a_palm_laid_on_the_body_lays_the_dex3_thumb_along_the_palm(robot):
    """Flat hand: unfolded, the Dex3 thumb stands ~10 cm out of the palm face; fully folded it
    lies along the palm (< 3 cm proud). Weight 0 changes nothing; a thumb flexed further than the
    weight keeps its value; opposition (thumb_0) and the fingers are kept."""
    hq, names = retarget_hands(_pose("flat"), robot)
    hq = np.repeat(hq, 3, 0)
    w = np.array([[0.0, 0.0], [0.0, 1.0], [0.0, 0.3]])
    folded = fold_thumbs(hq, names, robot, w)
    np.testing.assert_array_equal(folded[0], hq[0])
    thumb = [names.index(f"right_hand_thumb_{k}_joint") for k in (1, 2)]
    others = [i for i in range(len(names)) if i not in thumb]
    np.testing.assert_array_equal(folded[:, others], hq[:, others])
    for c in thumb:
        j = robot.joint_index(names[c])
        closed = robot.lower[j] if abs(robot.lower[j]) >= abs(robot.upper[j]) else robot.upper[j]
        assert folded[1, c] == pytest.approx(closed)
        assert folded[2, c] == pytest.approx(0.3 * closed)
    fist, _ = retarget_hands(_pose("fist"), robot)
    np.testing.assert_array_equal(fold_thumbs(fist, names, robot, np.array([[0.0, 0.3]])), fist)

    def full(h):
        q = robot.tpose.copy()
        q[[robot.joint_index(n) for n in names]] = h
        return q
    assert _thumb_protrusion_mm(robot, full(hq[0])) > 80.0
    assert _thumb_protrusion_mm(robot, full(folded[1])) < 30.0


def test_palm_rest_weight_needs_near_facing_and_a_free_thumb():
    near, radius = 0.05, 0.2
    assert palm_rest_weight(np.array([near]), np.array([0.9]), np.array([0.1]), radius)[0] == pytest.approx(1.0)
    assert palm_rest_weight(np.array([radius]), np.array([0.9]), np.array([0.1]), radius)[0] == 0.0
    assert palm_rest_weight(np.array([near]), np.array([-0.2]), np.array([0.1]), radius)[0] == 0.0
    assert palm_rest_weight(np.array([near]), np.array([0.9]), np.array([0.8]), radius)[0] == 0.0
    w = palm_rest_weight(np.linspace(0.0, 0.3, 31), np.full(31, 0.9), np.zeros(31), radius)
    assert np.all(np.diff(w) <= 1e-12)  # no more fold further away


def test_rate_limit_keeps_fingers_within_their_velocity_limits_symmetrically():
    """A finger target flipping faster than the joint can move (a jittering human) comes out
    within the velocity limits, with no lag (a spike is cut the same on both sides), and a
    target the joint can follow is returned unchanged."""
    from embody.retarget.limits import velocity_violations
    fps, vmax = 30.0, np.array([3.0, 6.0])
    q = np.zeros((21, 2))
    q[10] = [1.0, -1.0]  # a one-frame spike
    out = rate_limit(q, vmax, fps)
    assert velocity_violations(out, vmax, fps) == 0
    np.testing.assert_allclose(out[::-1], out, atol=1e-12)  # symmetric in time
    assert out[10, 0] == pytest.approx(0.5 * (3.0 / fps) * 2)  # mean of the two one-sided ramps' peaks
    slow = np.linspace(0.0, 1.0, 61)[:, None] * np.array([[1.0, -1.0]])  # 0.5 rad/s
    np.testing.assert_allclose(rate_limit(slow, vmax, fps), slow, atol=1e-12)
