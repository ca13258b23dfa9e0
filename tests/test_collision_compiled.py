"""The compiled (numba) collision kernels against the tensor versions they replace on the CPU:
the broad phase's rows, the narrow phase's selection (bit for bit in float32), the point
depths and their hand-written gradient, and the compiled FK with its gradient."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.collision.energy import (_blend, _contacts_torch, _penetrations_compiled,
                                     _penetrations_torch, _skin, _to_part, contacts,
                                     penetrations, point_depths)
from collision_cases import body, model  # noqa: F401 (fixtures)
from collision_cases import crossing_poses as clash_poses


def crossing_poses() -> np.ndarray:
    """The energy tests' crossing poses (arms into the hips, hands through the chest, hands
    clasped, fingers curled) plus random arm and finger poses (seeded)."""
    base = clash_poses()
    rng = np.random.default_rng(0)
    extra = base[2:4].copy()
    extra[:, 13:] += rng.normal(0.0, 0.3, (2, 42, 3))
    return np.concatenate([base, extra])


def _transforms(body, dtype=torch.float32) -> torch.Tensor:
    return body.joint_transforms(torch.as_tensor(crossing_poses(), dtype=dtype),
                                 torch.zeros(10, dtype=dtype))


@pytest.mark.parametrize("margin", [0.0, 0.005, 0.022])
def test_broad_phase_rows_match_the_tensor_version(body, model, margin):
    """Same chunk rows and point rows, in the same order (the compiled tests are the tensor
    version's in float64: on these poses no row sits at a margin within rounding)."""
    tr = _transforms(body)
    a, b = _contacts_torch(model, tr, margin), contacts(model, tr, margin)
    assert len(a.t) > 0 and len(a.points.t) > 0
    for f in "thabk":
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    for f in ("t", "h", "n", "b", "k", "first", "inverse", "part_first", "part_inverse",
              "part_point", "chunk_first", "slot"):
        assert torch.equal(getattr(a.points, f), getattr(b.points, f)), f


@pytest.mark.parametrize("tolerance", [-0.002, 0.0, 0.001])
def test_narrow_selection_is_the_tensor_one_bit_for_bit(body, model, tolerance):
    """float32 on the CPU: the compiled selection reproduces torch's float32 rounding (MKL's
    products included), so points, planes and plane values are identical."""
    tr = _transforms(body)
    d = model.tensors(tr.dtype, tr.device)
    reach = max(0.0, -tolerance)
    p = contacts(model, tr, 0.022).points
    a = _penetrations_torch(model, d, tr, tolerance, reach, p)
    b = _penetrations_compiled(model, d, tr, tolerance, reach, p)
    assert a is not None and len(a.t) > 100
    for f in ("t", "h", "n", "b", "plane", "f"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def _torch_depths(model, transforms, sel):
    d = model.tensors(transforms.dtype, transforms.device)
    g = transforms[:, d["part_joints"]]
    ql = _to_part(g[..., :3, :3], g[..., :3, 3], sel.t, sel.b,
                  _skin(d, _blend(d, transforms), sel.t, sel.h, sel.n))
    nd = sel.plane.to(transforms.dtype)
    return -(ql * nd[:, :3]).sum(-1) - nd[:, 3]


def test_point_depths_and_gradient_match_autograd(body, model):
    """The compiled depths and their hand-written gradient equal the autograd graph's in
    float64 (to rounding), and pass gradcheck."""
    tr = _transforms(body, torch.float64)
    sel = penetrations(model, tr, -0.002)
    assert sel is not None and len(sel.t) > 100
    leaf = tr.clone().requires_grad_()
    w = torch.rand(len(sel.t), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    a = point_depths(model, leaf, sel)
    g_a, = torch.autograd.grad((a * w).sum(), leaf)
    b = _torch_depths(model, leaf, sel)
    g_b, = torch.autograd.grad((b * w).sum(), leaf)
    assert torch.allclose(a, b, rtol=0, atol=1e-12)
    assert torch.allclose(g_a, g_b, rtol=1e-10, atol=1e-10)
    few = type(sel)(sel.t[::50], sel.h[::50], sel.n[::50], sel.b[::50], sel.plane[::50])
    assert torch.autograd.gradcheck(lambda x: point_depths(model, x, few),
                                    (tr[:, :].clone().requires_grad_(),))


def test_compiled_fk_matches_the_torch_fk(body):
    """Values (float32 to rounding, float64 to 1e-12), gradients against autograd, gradcheck
    (also at zero and tiny angles: Rodrigues' series branch); the offsets and the root are
    constants, so gradients for them are refused."""
    rng = torch.Generator().manual_seed(1)
    pose = 0.4 * torch.randn(6, 55, 3, generator=rng)
    pose[0, :20], pose[1, :20] = 0.0, 1e-4 * torch.randn(20, 3, generator=rng)
    betas = 0.5 * torch.randn(10, generator=rng)
    for dtype, atol in ((torch.float32, 1e-5), (torch.float64, 1e-12)):
        p = pose.to(dtype).requires_grad_()
        w = torch.randn(6, 54, 4, 4, generator=rng).to(dtype)
        a = body.joint_transforms(p, betas.to(dtype))
        g_a, = torch.autograd.grad((a * w).sum(), p)
        b = body.joint_transforms_compiled(p, betas.to(dtype))
        g_b, = torch.autograd.grad((b * w).sum(), p)
        assert torch.allclose(a, b, rtol=0, atol=atol)
        assert torch.allclose(g_a, g_b, rtol=1e-4 if dtype == torch.float32 else 1e-10,
                              atol=atol * 10)
    p = pose[:2].double().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda x: body.joint_transforms_compiled(x, betas.double()), (p,))
    with pytest.raises(ValueError):
        body.joint_transforms(pose, betas.clone().requires_grad_(), compiled=True)
