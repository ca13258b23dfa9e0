"""Gauss-Newton mitigation (`embody.collision.solve`): analytic Jacobians against finite
differences, the block-banded solve against a dense one, and the solve's behaviour."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.body import MannequinBody
from embody.collision import mitigate
from embody.collision import solve as S
from embody.collision.capsules import arm_capsules
from embody.collision.energy import collision_model, contacts
from embody.collision.masks import mask_joints
from embody.config.collision import CollisionConfig
from embody.motion import JOINT_NAMES
from tests.test_collision_optimize import colliding_motion


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


def _problem(body, motion):
    names = list(body.joint_names)
    keep = [j for j in mask_joints("arms") if JOINT_NAMES[j] in names]
    dt = torch.float64
    return S._Problem(body, collision_model(body, motion.betas, vertex_stride=8),
                      arm_capsules(body, motion.betas, ()), CollisionConfig(),
                      torch.as_tensor(motion.pose, dtype=dt),
                      torch.ones(motion.num_frames, dtype=dt), torch.zeros(10, dtype=dt),
                      np.array(keep), np.array([names.index(JOINT_NAMES[j]) for j in keep]),
                      torch.as_tensor(S._descendants(np.asarray(body.parents)), dtype=dt))


def test_analytic_jacobians_match_finite_differences(body):
    pb = _problem(body, colliding_motion(6))
    u = torch.randn(6, len(pb.mask_pose), 3, generator=torch.Generator().manual_seed(0),
                    dtype=torch.float64) * 0.05
    x = pb.pose(u)
    tr = body.joint_transforms(x, pb.betas)
    rows = contacts(pb.model, tr, 0.02).points
    ext = S._external_planes(pb.model, S.external_faces(body, pb.model, np.zeros(10), 0.10),
                             torch.float64)
    pb.jr = S.right_jacobian(x[:, pb.mask_pose])
    sel = S._select(pb.model, ext, rows, tr, 0.0)
    jd = S._point_jacobian(pb, sel, tr)
    sub = S._point_jacobian(pb, sel, tr, np.array([2, 5]))
    # a column subset is the same product over fewer columns: float64 round-off apart
    assert torch.allclose(sub, jd[:, [2, 5]], rtol=1e-12, atol=1e-15)
    ov, _, jc = S._capsule_terms(pb, tr, x, True)
    assert len(sel.t) > 100 and len(ov) > 0
    eps = 1e-6
    for k in (2, 5, 8):  # shoulder, elbow, a finger of the arms mask
        for c in range(3):
            du = torch.zeros_like(u)
            du[:, k, c] = eps
            x2 = pb.pose(u + du)
            tr2 = body.joint_transforms(x2, pb.betas)
            # the same points and planes, moved: depth behind the selected plane
            from embody.collision.energy import Penetrations, point_depths
            pen = Penetrations(sel.t, sel.h, sel.n, sel.b, sel.plane)
            fd = (point_depths(pb.model, tr2, pen) - point_depths(pb.model, tr, pen)) / eps
            assert torch.allclose(fd, jd[:, k, c], atol=1e-5)
            o2, _, _ = S._capsule_terms(pb, tr2, x2, False)
            assert torch.allclose((o2 - ov) / eps, jc[:, k, c], atol=1e-5)


def test_external_faces_leave_the_region_and_deepen_the_push(body):
    """Faces where torso pieces abut are internal; inside a piece the depth to the external
    faces is at least the nearest-face depth, and the same points count as inside."""
    model = collision_model(body, np.zeros(10), vertex_stride=8)
    ext = S.external_faces(body, model, np.zeros(10), 0.10)
    real = model.planes[..., 3] != -1e9
    assert (ext <= real).all() and (ext.sum(1) > 0).all()
    spine = [i for i, n in enumerate(model.part_names) if n in ("spine1", "spine3")]
    pieces = np.isin(np.arange(len(model.planes)), model.part_pieces[spine].ravel())
    assert (~ext[pieces] & real[pieces]).any()  # some torso faces are internal
    motion = colliding_motion(6)
    dt = torch.float64
    tr = body.joint_transforms(torch.as_tensor(motion.pose, dtype=dt), torch.zeros(10, dtype=dt))
    rows = contacts(model, tr, 0.0).points
    own = S._external_planes(model, ext, dt)
    all_planes = S._external_planes(model, real, dt)  # every real face: the plain SDF
    a = S._select(model, own, rows, tr, 0.0)
    b = S._select(model, all_planes, rows, tr, 0.0)
    key = lambda s: set(zip(s.t.tolist(), s.h.tolist(), s.n.tolist(), s.b.tolist()))  # noqa: E731
    assert key(a) == key(b) and len(a.t) > 0
    assert a.depth.sum() >= b.depth.sum()


def test_banded_solve_matches_dense():
    rng = np.random.default_rng(0)
    n, bw = 150, 12
    a = np.zeros((n, n))
    for o in range(1, bw + 1):
        v = rng.normal(size=n - o) * 0.1
        a[np.arange(n - o), np.arange(o, n)] = v
        a[np.arange(o, n), np.arange(n - o)] = v
    a[np.arange(n), np.arange(n)] = 3.0
    ab = np.stack([np.r_[np.zeros(bw - r), np.diagonal(a, bw - r)] for r in range(bw + 1)])
    b = rng.normal(size=n)
    np.testing.assert_allclose(S._banded_solve(ab, b, bw), np.linalg.solve(a, b), atol=1e-10)


def test_gauss_newton_clears_a_planted_collision(body):
    motion = colliding_motion(6)
    cfg = CollisionConfig(solver="gauss_newton", depth_metrics=False, solver_iterations=8)
    r = mitigate(motion, body, cfg)
    m = r.metrics
    # 8 LM iterations, then Adam from there on the frames they leave penetrating
    assert m["improved"] and m["reduction_pct"] >= 90.0 and m["steps"] > 0
    assert m["energy_after"] == 0.0
    frozen = np.setdiff1d(np.arange(55), mask_joints("arms"))
    assert np.array_equal(r.motion.pose[:, frozen], motion.pose[:, frozen])


def test_gauss_newton_takes_a_planted_forearm_out_of_the_chest(body):
    """Issue 13's planted case on the LM path: under 3 mm by the mesh judge, far frames
    bit-identical, in a handful of iterations."""
    from tests.test_collision_depth import planted
    motion = planted(44, slice(20, 24))
    r = mitigate(motion, body, CollisionConfig(solver="gauss_newton", depth_polish=0.0))
    m = r.metrics
    assert m["max_depth_mm_before"] > 15.0
    assert m["max_depth_mm_after"] < 3.0 and m["frames_over_5mm_after"] == 0
    assert 0 < m["steps"] <= 20
    far = np.r_[0:5, 39:44]
    assert r.motion.pose[far].tobytes() == motion.pose[far].astype(r.motion.pose.dtype).tobytes()
