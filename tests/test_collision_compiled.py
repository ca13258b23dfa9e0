"""The compiled (numba) collision kernels against the tensor versions they replace on the CPU:
the broad phase's rows, the narrow phase's selection (to float32 rounding), the point
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


#: float32 rounding of a plane value (metres): products of O(1) rotations and O(0.1 m)
#: offsets summed over a few joints and planes; 1e-6 m is ~30 float32 ulps at 0.1 m.
F32_PLANE_ATOL = 1e-6


@pytest.mark.parametrize("tolerance", [-0.002, 0.0, 0.001])
def test_narrow_selection_matches_the_tensor_one(body, model, tolerance):
    """float32 on the CPU: the compiled selection and torch's agree to float32 rounding. The
    same (frame, point, part) rows are selected except rows whose plane value lies within
    rounding of the threshold; each common row has its plane value within rounding, and the
    same plane unless two planes of the part tie within rounding."""
    tr = _transforms(body)
    d = model.tensors(tr.dtype, tr.device)
    reach = max(0.0, -tolerance)
    p = contacts(model, tr, 0.022).points
    a = _penetrations_torch(model, d, tr, tolerance, reach, p)
    b = _penetrations_compiled(model, d, tr, tolerance, reach, p)
    assert a is not None and b is not None and len(a.t) > 100

    def rows(s):
        return {(int(t), int(h), int(n), int(k)): i
                for i, (t, h, n, k) in enumerate(zip(s.t, s.h, s.n, s.b))}

    ra, rb = rows(a), rows(b)
    common = sorted(set(ra) & set(rb))
    assert len(common) >= 0.99 * max(len(ra), len(rb))
    for only, s in ((set(ra) - set(rb), a), (set(rb) - set(ra), b)):
        for key in only:  # selected by one path only: on the threshold, to rounding
            assert abs(float(s.f[(ra if s is a else rb)[key]]) + tolerance) <= F32_PLANE_ATOL, key
    ia = torch.tensor([ra[k] for k in common])
    ib = torch.tensor([rb[k] for k in common])
    fa, fb = a.f[ia], b.f[ib]
    assert torch.allclose(fa, fb, rtol=0, atol=F32_PLANE_ATOL)
    same_plane = (a.plane[ia] == b.plane[ib]).all(dim=1)
    # a different active plane only where two planes of the part tie to rounding, which the
    # equal plane values above already show
    assert same_plane.float().mean() >= 0.99


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


def test_fk_over_a_subtree_is_the_whole_pass_bit_for_bit(body):
    """Changing only some joints' rotations: `forward_at` over their `subtree` updates the
    world transforms to exactly the whole pass's, and `backward_at` /
    `rodrigues_backward_frames` on some frames give exactly the whole backward's gradient for
    those joints and frames (the optimiser's objective relies on both)."""
    from embody.body.compiled_fk import (_rodrigues, _rodrigues_backward, backward_at,
                                         forward_at, rodrigues_at, rodrigues_backward_frames,
                                         subtree)
    src, off, root, parents, order = body.compiled_fk_inputs(torch.zeros(5, 55, 3),
                                                             torch.zeros(10))
    rng = np.random.default_rng(4)
    aa = rng.normal(0.0, 0.4, (5, len(src), 3))
    aa[0, :5] = 0.0  # Rodrigues' series branch
    moved = np.array([16, 18, 20, 37, 40], dtype=np.int64)
    sub = subtree(parents, order, moved)
    assert set(moved) <= set(sub) and len(sub) < len(order)
    assert all(parents[j] in sub for j in sub if j not in moved)  # descendants only

    def whole(a):
        local, world = np.empty((5, len(src), 3, 3)), np.empty((5, len(src), 4, 4))
        _rodrigues(a, local)
        forward_at(local, off, root, parents, order, world)
        return local, world

    local, world = whole(aa)
    new = aa.copy()
    new[:, moved] += rng.normal(0.0, 0.2, (5, len(moved), 3))
    coefficients = np.zeros((5, len(src), 2))
    rodrigues_at(new, moved, local, coefficients)
    forward_at(local, off, root, parents, sub, world)
    local_ref, world_ref = whole(new)
    assert np.array_equal(local, local_ref) and np.array_equal(world, world_ref)
    grad = rng.normal(0.0, 1.0, (5, len(src), 4, 4))
    g_ref = np.empty((5, len(src), 3, 3))
    backward_at(local_ref, world_ref, off, parents, order, grad, np.arange(5), g_ref)
    aa_ref = np.empty((5, len(src), 3))
    _rodrigues_backward(new, g_ref, aa_ref)
    frames = np.array([0, 3], dtype=np.int64)
    g_local, g_aa = np.zeros((5, len(src), 3, 3)), np.zeros((5, len(src), 3))
    backward_at(local, world, off, parents, sub, grad, frames, g_local)
    rodrigues_backward_frames(new, coefficients, g_local, frames, moved, g_aa)
    assert np.array_equal(g_aa[frames][:, moved], aa_ref[frames][:, moved])
    assert not g_aa[[1, 2, 4]].any()  # the other frames are left as they were


def test_broad_phase_limit_test_is_the_root_comparison():
    """`broad._below` (squared distance against a squared limit, the root only near it)
    answers as `sqrt(d2) < limit` / `<= limit`, at and around the limit and for 0 and
    negative limits."""
    from embody.collision.broad import _below
    rng = np.random.default_rng(5)
    limits = np.concatenate([rng.uniform(1e-4, 1.0, 400), [0.0, -0.01, 0.022]])
    for limit in limits:
        roots = limit + np.concatenate([rng.normal(0.0, 1e-3, 40), [0.0],
                                        np.spacing(abs(limit)) * np.arange(-3, 4)])
        for d2 in np.concatenate([np.abs(roots) ** 2, [0.0, limit * limit]]):
            assert _below(d2, limit, True) == (np.sqrt(d2) < limit)
            assert _below(d2, limit, False) == (np.sqrt(d2) <= limit)
