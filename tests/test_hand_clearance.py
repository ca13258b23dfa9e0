"""Hand clearance at hand scale: the term's Jacobian, and a two-handed sign whose human hands part
after touching keeps the robot's hands apart by the human's gap at hand scale (no false contact),
while the touch itself stays a touch without penetration."""

import numpy as np
import pytest

from embody.body import load_body_model
from embody.config import Config
from embody.metrics.embodiments import robot_contacts
from embody.motion import Motion
from embody.retarget import build_targets, solve
from embody.retarget.costs import Pose
from embody.retarget.hand_clearance import HandClearanceTerm
from embody.retarget.shape_fit import fit as run_fit
from embody.robot import load_robot
from embody.synth.generator import generate_sequence


@pytest.fixture(scope="module")
def setup():
    cfg = Config()
    robot, body = load_robot(cfg.robot), load_body_model(cfg.body)
    return cfg, robot, body, run_fit(robot, body, cfg.ik.model_copy(update={"shape_iterations": 150}))


def test_jacobian_matches_finite_differences(setup):
    _, robot, _, _ = setup
    rng = np.random.default_rng(0)
    q = np.tile(robot.tpose, (3, 1))
    ik = np.flatnonzero(robot.ik_mask)
    q[:, ik] += rng.normal(0.0, 0.3, (3, len(ik)))
    q = np.clip(q, robot.lower, robot.upper)
    term = HandClearanceTerm(robot, np.full((3, 5), 0.5), 4.0)  # 50 cm: every hull row active (face too)
    fk = robot.fk(term.bodies)
    mask = fk.moves(list(ik))

    def rows(qq):
        rot, pos = fk.forward(qq)
        return term.rows(Pose(rot, pos, fk.index, mask), 1.0)

    r, jac = rows(q)
    rot, pos = fk.forward(q)
    z, o = fk.joint_frames(rot, pos, list(ik))
    j = jac(z, o)
    assert r.shape == (3, term.width) and (r > 0).sum() >= 2
    h = 1e-6
    for col in rng.choice(len(ik), 6, replace=False):
        dq = np.zeros_like(q)
        dq[:, ik[col]] = h
        fd = (rows(q + dq)[0] - rows(q - dq)[0]) / (2 * h)
        np.testing.assert_allclose(j[:, :, col], fd, atol=2e-4)  # a closest point may switch


def test_parting_hands_keep_their_gap_at_hand_scale(setup):
    """FRIEND (default sequence 6): the human's hands touch, then part by 2.5-3.6 cm."""
    cfg, robot, body, fit = setup
    m = generate_sequence(0, 6)
    sl = slice(45, 95)
    motion = Motion(pose=np.asarray(m.pose)[sl], transl=np.zeros((50, 3)), betas=np.asarray(m.betas), fps=m.fps)
    targets = build_targets(motion, body, fit, robot, cfg.ik)
    gap = targets.hand_gap[:, 0]
    q = solve(robot, targets, cfg.ik).q
    off = solve(robot, targets, cfg.ik.model_copy(update={"w_hand_clearance": 0.0})).q
    d, d_off = robot_contacts(robot, q)[:, 0], robot_contacts(robot, off)[:, 0]
    eps_r = 0.015 * 1.42  # the robot's contact ε at hand scale (Dex3)
    parted = gap > 0.03  # the human's hands 2.1+ cm apart
    assert parted.sum() >= 5 and gap.max() <= cfg.ik.hand_gap_max + 1e-12
    assert np.all(d[parted] > eps_r)  # no false contact where the human's hands are apart
    assert np.mean(d[parted] >= gap[parted] - 0.01) > 0.8  # and about the asked gap
    near = parted & (gap < cfg.ik.hand_gap_max)  # the human's hands 2.1-3.5 cm apart
    assert near.sum() >= 5 and np.mean(d_off[near] < eps_r) > 0.5  # without the term most "touch"
    assert np.all(d > -0.002)  # no penetration anywhere
    touching = gap == 0.0
    assert np.mean(d[touching] < eps_r) > 0.9  # and the touches stay touches


def _random_q(robot, rng: np.random.Generator, t: int) -> np.ndarray:
    """t random configurations: the T-pose with N(0, 0.6) on the IK joints, within limits."""
    q = np.tile(robot.tpose, (t, 1))
    ik = np.flatnonzero(robot.ik_mask)
    q[:, ik] += rng.normal(0.0, 0.6, (t, len(ik)))
    return np.clip(q, robot.lower, robot.upper)


def test_culled_rows_equal_the_brute_force_rows(setup):
    """The exact cull (a few planes' lower bound against the gap) changes no residual: every row
    equals min over all hand points of the full max-plane value, at the asked gap."""
    _, robot, _, _ = setup
    rng = np.random.default_rng(1)
    t = 60
    q = _random_q(robot, rng, t)
    ik = np.flatnonzero(robot.ik_mask)
    gap = rng.uniform(0.0, 0.4, (t, 3)) * (rng.random((t, 3)) < 0.8)
    term = HandClearanceTerm(robot, gap, 4.0)
    fk = robot.fk(term.bodies)
    rot, pos = fk.forward(q)
    pose = Pose(rot, pos, fk.index, fk.moves(list(ik)))
    r, _ = term.rows(pose, 1.0)
    px, expected, row = term.px, np.zeros_like(r), 0
    for c, pts, hulls in term.pairs:
        col = np.array([fk.index[px.bodies[b]] for b in px.sphere_body[pts]])
        x = pos[:, col] + np.einsum("fpab,pb->fpa", rot[:, col], px.centres[pts])
        for h in hulls:
            hcol = fk.index[px.bodies[px.hull_body[h]]]
            xl = np.einsum("fba,fpb->fpa", rot[:, hcol], x - pos[:, hcol][:, None])
            value = (xl @ px.hull_planes[h][:, :3].T + px.hull_planes[h][:, 3]).max(-1) - px.radii[pts]
            expected[:, row] = 2.0 * np.maximum(gap[:, c] - value.min(1), 0.0)
            row += 1
    # the cull (cluster balls, then points, each against a few planes' lower bound) is exact
    assert (expected > 0).sum() > 10 and len(term.bound_planes[term.pairs[0][2][0]]) < px.hull_planes.shape[1]
    np.testing.assert_allclose(r, expected, atol=1e-12)


def test_a_hand_passing_the_face_does_not_brush_the_robot_face(setup, monkeypatch):
    """SHOULDER (default sequence 7): the human's right hand passes 2.6-2.9 cm from the face on its
    way to the left shoulder (no contact); the robot's bigger hand kept the face channel's gap
    (capped at `FACE_GAP_MAX`) and is not a robot contact there, where without the face channel
    it was; no penetration."""
    import embody.retarget.targets as targets_mod
    cfg, robot, body, fit = setup
    m = generate_sequence(0, 7)
    sl = slice(70, 100)
    motion = Motion(pose=np.asarray(m.pose)[sl], transl=np.zeros((30, 3)), betas=np.asarray(m.betas), fps=m.fps)
    targets = build_targets(motion, body, fit, robot, cfg.ik)
    gap = targets.hand_gap[:, 4]  # right_face
    assert gap.max() <= targets_mod.FACE_GAP_MAX + 1e-12
    q = solve(robot, targets, cfg.ik).q
    monkeypatch.setattr(targets_mod, "FACE_GAP_MAX", 0.0)
    off = solve(robot, build_targets(motion, body, fit, robot, cfg.ik), cfg.ik).q
    d, d_off = robot_contacts(robot, q)[:, 2], robot_contacts(robot, off)[:, 2]  # right_face
    eps_r = 0.015 * 1.42
    apart = gap > 0.0
    assert apart.sum() >= 5
    assert np.mean(d[apart] > eps_r) > 0.9
    assert np.sum(d_off[apart] < eps_r) > np.sum(d[apart] < eps_r)
    assert np.all(d > -0.002)


def test_compiled_rows_match_the_numpy_reference(setup, monkeypatch):
    """The compiled rows (`_closest`: each (frame, hull)'s closest hand point, culled as the
    NumPy form culls; and the NumPy form's own compiled plane pass, `proxy_hulls.max_planes`)
    give the NumPy form's rows and Jacobian: the same arithmetic, so equal to round-off (NumPy's
    matmuls may fuse multiply-adds)."""
    from embody.retarget import proxy_hulls

    _, robot, _, _ = setup
    rng = np.random.default_rng(2)
    t = 40
    q = _random_q(robot, rng, t)
    ik = np.flatnonzero(robot.ik_mask)
    term = HandClearanceTerm(robot, rng.uniform(0.0, 0.4, (t, 5)) * (rng.random((t, 5)) < 0.8), 4.0)
    # the kernel alone, on random points against every hull of the first pair
    planes = term.exact_planes[0]
    xl = rng.normal(0.0, 0.05, (500, 3))
    hull = rng.integers(0, len(planes), 500)
    value, normal = proxy_hulls.max_planes(xl, hull, *term.plane_tables[0])
    ref_value, ref_normal = proxy_hulls.max_planes_numpy(xl, hull, planes)
    np.testing.assert_allclose(value, ref_value, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(normal, ref_normal)
    # the term's rows and Jacobian, compiled against the reference
    fk = robot.fk(term.bodies)
    rot, pos = fk.forward(q)
    pose = Pose(rot, pos, fk.index, fk.moves(list(ik)))
    z, o = fk.joint_frames(rot, pos, list(ik))
    r, jac = term.rows(pose, 1.0)
    monkeypatch.setattr(HandClearanceTerm, "compiled", False)
    r_np, jac_np = term.rows(pose, 1.0)  # NumPy cull, compiled plane pass
    monkeypatch.setattr(HandClearanceTerm, "planes", staticmethod(proxy_hulls.max_planes_numpy))
    r_ref, jac_ref = term.rows(pose, 1.0)  # all NumPy
    assert (r_ref > 0).sum() > 10
    for rows, jacobian in ((r, jac), (r_np, jac_np)):
        np.testing.assert_allclose(rows, r_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(jacobian(z, o), jac_ref(z, o), rtol=0, atol=1e-12)
