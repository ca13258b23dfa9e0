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
from embody.collision.energy import collision_model
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
    cand = S._candidates(pb.model, tr, 0.02)
    pb.jr = S.right_jacobian(x[:, pb.mask_pose])
    dep_all, _, _ = S._point_terms(pb, cand, tr, x, 0.0, False)
    dep, _, jd = S._point_terms(pb, cand, tr, x, 0.0, True)
    ov, _, jc = S._capsule_terms(pb, tr, x, True)
    assert len(dep) > 100 and len(ov) > 0
    eps = 1e-6
    for k in (2, 5, 8):  # shoulder, elbow, a finger of the arms mask
        for c in range(3):
            du = torch.zeros_like(u)
            du[:, k, c] = eps
            x2 = pb.pose(u + du)
            tr2 = body.joint_transforms(x2, pb.betas)
            d2, _, _ = S._point_terms(pb, cand, tr2, x2, 0.0, False)
            fd = (d2[dep_all > 0] - dep) / eps
            assert torch.allclose(fd, jd[:, k, c], atol=1e-5)
            o2, _, _ = S._capsule_terms(pb, tr2, x2, False)
            assert torch.allclose((o2 - ov) / eps, jc[:, k, c], atol=1e-5)


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
    assert m["improved"] and m["reduction_pct"] >= 90.0 and 0 < m["steps"] <= 8
    frozen = np.setdiff1d(np.arange(55), mask_joints("arms"))
    assert np.array_equal(r.motion.pose[:, frozen], motion.pose[:, frozen])
