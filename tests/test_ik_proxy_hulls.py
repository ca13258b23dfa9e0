"""The IK's compiled sphere/hull proxy contacts (`proxy_hulls.hull_contacts`) against the NumPy
reference (`hull_contacts_numpy`): the same pairs, clearances, points and normals, so the same
collision rows, Jacobian and IK solution."""

import numpy as np
import pytest

from embody.config.ik import IKConfig
from embody.retarget import costs
from embody.retarget.costs import Residuals
from embody.retarget.ik import solve
from embody.retarget.proxy_hulls import hull_contacts, hull_contacts_numpy
from embody.robot import load_robot
from tests.test_retarget_ik import _smooth_random_q, _targets_from_q


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _plant(robot, left, right, t=4):
    """Wrist targets (torso frame) from the rest pose."""
    targets = _targets_from_q(robot, np.tile(robot.rest, (t, 1)))
    targets.wrist_pos[:, 0] = left
    targets.wrist_pos[:, 1] = right
    return targets


@pytest.fixture(scope="module")
def poses(robot):
    """Random configurations, hands overlapping in front of the chest, and hands pushed into the
    torso (the IK without its collision term)."""
    rng = np.random.default_rng(0)
    qs = [rng.uniform(robot.lower, robot.upper, size=(96, robot.n_joints)),
          _smooth_random_q(robot, 24, seed=3)]
    free = IKConfig(w_collision=0.0, contact_repair=False, iterations=15)
    for left, right in (([0.30, 0.05, 0.10], [0.30, -0.05, 0.10]),  # hands overlap
                        ([0.02, 0.08, 0.05], [0.02, -0.08, 0.05])):  # hands inside the torso
        qs.append(solve(robot, _plant(robot, left, right), free).q)
    return np.concatenate(qs)


def test_compiled_contacts_match_the_numpy_reference(robot, poses):
    res = Residuals(robot, _targets_from_q(robot, poses), IKConfig())
    rot, pos = res.fk.forward(poses)
    for margin in (res.cfg.collision_margin, 0.0):  # also a margin tighter than the tables'
        tc, qc, value, x, normal = hull_contacts(res.hulls, rot, pos, margin)
        ref = hull_contacts_numpy(res.hulls, rot, pos, margin)
        assert np.array_equal(tc, ref[0]) and np.array_equal(qc, ref[1])
        for got, want in zip((value, x, normal), ref[2:]):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
        assert np.all(np.diff(tc) >= 0) and np.all((np.diff(qc) > 0) | (np.diff(tc) > 0))  # frame, pair
        assert np.all(value < margin)
    # the planted poses really are deep contacts: hands into each other and into the torso shell
    hull_names = [res.proxies.bodies[b] for b in res.proxies.hull_body]
    deep = value < -0.01
    hulls = {hull_names[h] for h in res.hulls.pair_hull[qc[deep]]}
    assert "torso_link" in hulls and any("hand" in n or "wrist" in n for n in hulls)
    assert len(np.unique(tc)) > 50


def test_collision_rows_and_jacobian_match_the_reference(robot, poses):
    res = Residuals(robot, _targets_from_q(robot, poses), IKConfig())
    rot, pos = res.fk.forward(poses)
    r, jac = res._collision(rot, pos)
    r_ref, jac_ref = res._collision(rot, pos, hulls=hull_contacts_numpy)
    assert r.shape == r_ref.shape and r.shape[1] > 0 and (r > 0).sum() > 100
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-10)
    z, o = res.fk.joint_frames(rot, pos, list(res.ik))
    np.testing.assert_allclose(jac(z, o), jac_ref(z, o), rtol=0, atol=1e-10)


def test_ik_solution_matches_the_reference(robot, monkeypatch):
    targets = _plant(robot, [0.30, 0.05, 0.10], [0.30, -0.05, 0.10], t=6)
    cfg = IKConfig(contact_repair=False)
    compiled = solve(robot, targets, cfg)
    monkeypatch.setattr(costs, "hull_contacts", hull_contacts_numpy)  # the reference, everywhere
    reference = solve(robot, targets, cfg)
    assert np.abs(compiled.q - reference.q).max() < 1e-8
    assert compiled.metrics["self_collision_frames"] == reference.metrics["self_collision_frames"] == 0
