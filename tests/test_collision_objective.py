"""Adam's objective by hand (`collision.objective`): its values and gradient are autograd's
through the same kernels (`optimize._optimise`'s graph)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.body import MannequinBody
from embody.collision import collision_model
from embody.collision.capsules import arm_capsules, capsule_energies
from embody.collision.energy import contacts, frame_energies, frame_energies_and_exact
from embody.collision.masks import mask_joints
from embody.collision.objective import Objective
from embody.config.collision import CollisionConfig
from test_collision_compiled import crossing_poses


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("check", [False, True])
def test_hand_gradient_is_autograds(dtype, check):
    body, cfg = MannequinBody(), CollisionConfig()
    model = collision_model(body, vertex_stride=4)
    caps = arm_capsules(body, np.zeros(10))
    rng = np.random.default_rng(3)
    x0 = torch.as_tensor(crossing_poses(), dtype=dtype)
    t = x0.shape[0]
    idx = mask_joints(cfg.mask, cfg.joints)
    jidx = torch.as_tensor(idx)
    w = torch.as_tensor(np.linspace(0.3, 1.0, t), dtype=dtype)[:, None, None]
    live = torch.as_tensor([1, 1, 1, 0, 1, 1, 1], dtype=dtype)
    lam = torch.as_tensor(rng.uniform(10, 100, t), dtype=dtype)
    u = torch.as_tensor(rng.normal(0, 0.05, (t, len(idx), 3)), dtype=dtype)
    betas = torch.zeros(10, dtype=dtype)
    tol, exact_tol = cfg.tolerance - cfg.clearance, cfg.tolerance
    obj = Objective(body.compiled_fk_inputs(x0, betas), model, x0, w, jidx, live, caps,
                    cfg.capsule_weight, cfg.lambda_close, cfg.lambda_smooth)
    tr = obj.pose(u)
    near = contacts(model, tr, 0.022)
    e, exact = obj.energies(near, tol, exact_tol if check else None)
    value, grad = obj.gradient(lam)
    # autograd through the optimiser's graph
    ua = u.clone().requires_grad_(True)
    delta = torch.zeros_like(x0).index_copy(1, jidx, ua) * w
    x = x0 + delta
    tra = body.joint_transforms_compiled(x, betas)
    torch.testing.assert_close(tr, tra.detach(), rtol=0, atol=0)
    if check:
        ea, xa = frame_energies_and_exact(model, tra, tol, exact_tol, near)
        torch.testing.assert_close(exact, xa * live, rtol=0, atol=0)
    else:
        ea = frame_energies(model, tra, tol, near)
    ea = ea * live + cfg.capsule_weight * capsule_energies(caps, tra, compiled=True) * live
    s2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    oa = (lam * ea).sum() / t + cfg.lambda_close * (delta ** 2).sum() / t \
        + cfg.lambda_smooth * (s2 ** 2).sum() / t
    oa.backward()
    assert (e > 0).sum() >= 3
    torch.testing.assert_close(e, ea.detach(), rtol=0, atol=0)
    assert value == pytest.approx(float(oa.detach()), rel=1e-6 if dtype == torch.float32 else 1e-12)
    scale = float(ua.grad.abs().max())
    assert scale > 0
    tol_g = 1e-5 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(grad, ua.grad, rtol=tol_g, atol=tol_g * scale)
