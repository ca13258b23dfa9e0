"""The self-collision energy (Eq. 1) on the mannequin: zeros, a brute-force reference on the
skinned mesh, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.collision import collision_model, frame_energies, part_volumes
from embody.collision.energy import _blend, _chunk_spheres, skinned_points
from embody.collision.exclusions import checked_pairs, group_name, part_groups
from embody.errors import ConfigError
from embody.motion import JOINT_NAMES
from collision_cases import body, crossing_poses, model  # noqa: F401 (fixtures)

J = JOINT_NAMES.index


def reference_energies(body, pose: np.ndarray, stride: int, tolerance: float = 0.0,
                       allow=()) -> np.ndarray:
    """Eq. 1 by brute force: every `stride`-th vertex of each part, skinned densely (LBS with
    all J weights) for the whole mesh, plus the pieces' corners carried by their joint, against
    every piece of every checked part."""
    vols = part_volumes(body)
    groups, part_group = part_groups(vols.part_names)
    checked = checked_pairs(groups, body.joint_names, body.parents, allow)
    betas = torch.zeros(10, dtype=torch.float64)
    rest = body.rest_vertices(betas).numpy()
    g_rest = body.joint_transforms(torch.zeros(1, 55, 3, dtype=torch.float64), betas)[0].numpy()
    g = body.joint_transforms(torch.as_tensor(pose, dtype=torch.float64), betas).numpy()
    weights = body.skin_weights.astype(np.float64)
    out = np.zeros(len(pose))
    for t in range(len(pose)):
        blend = np.einsum("vj,jab->vab", weights, (g[t] @ np.linalg.inv(g_rest))[:, :3])
        skinned = np.einsum("vab,vb->va", blend[..., :3], rest) + blend[..., 3]
        for a, ja in enumerate(vols.part_joints):
            corners = np.concatenate([pc.vertices[::stride] for pc in vols.pieces if pc.part == a])
            world = np.concatenate([skinned[vols.vertex_parts == a][::stride],
                                    corners @ g[t, ja, :3, :3].T + g[t, ja, :3, 3]])
            for b, jb in enumerate(vols.part_joints):
                if not checked[part_group[a], part_group[b]]:
                    continue
                q = (world - g[t, jb, :3, 3]) @ g[t, jb, :3, :3]
                f = np.min([np.max(q @ pc.planes[:, :3].T + pc.planes[:, 3], axis=1)
                            for pc in vols.pieces if pc.part == b], axis=0)
                out[t] += (np.maximum(0.0, -f - tolerance) ** 2).sum()
    return out


def energies(body, model, pose, tolerance=0.0) -> np.ndarray:
    p = torch.as_tensor(pose, dtype=torch.float64)
    return frame_energies(model, body.joint_transforms(p, torch.zeros(10, dtype=torch.float64)),
                          tolerance).numpy()


def test_tpose_and_relaxed_poses_are_free(body, model):
    pose = np.zeros((3, 55, 3))
    pose[1, J("left_shoulder"), 2], pose[1, J("right_shoulder"), 2] = -1.2, 1.2  # arms down
    pose[2, J("left_elbow"), 1], pose[2, J("right_elbow"), 1] = -1.0, 1.0        # elbows bent
    assert np.array_equal(energies(body, model, pose), np.zeros(3))


def test_negative_tolerance_adds_a_clearance_band(body, model):
    """The optimiser's clearance target: points within 2 cm outside a piece count too."""
    pose = np.zeros((2, 55, 3))
    pose[:, J("left_shoulder"), 2], pose[:, J("right_shoulder"), 2] = -1.4, 1.4   # hands by hips
    pose[1] = crossing_poses()[3]
    plain, band = energies(body, model, pose), energies(body, model, pose, -0.02)
    assert plain[0] == 0.0 and band[0] > 0.0
    assert band[1] > plain[1] > 0.0


def test_matches_brute_force_reference(body, model):
    pose = crossing_poses()
    ours = energies(body, model, pose)
    ref = reference_energies(body, pose, stride=4)
    assert ours[0] == 0.0 and (ours[1:] > 1e-4).all()
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-12)
    tol = 0.005
    np.testing.assert_allclose(energies(body, model, pose, tol),
                               reference_energies(body, pose, 4, tol), rtol=1e-9, atol=1e-12)


def test_gradient_matches_finite_differences(body, model):
    pose = torch.as_tensor(crossing_poses()[2:4], dtype=torch.float64)
    betas = torch.zeros(10, dtype=torch.float64)
    joints = [J("left_shoulder"), J("right_elbow")]

    def f(x: torch.Tensor) -> torch.Tensor:
        p = pose.clone()
        p[:, joints] = x
        return frame_energies(model, body.joint_transforms(p, betas)).sum()

    x = pose[:, joints].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(x), x)
    eps = 1e-6
    fd = torch.zeros_like(grad)
    with torch.no_grad():
        for idx in np.ndindex(*x.shape):
            dx = torch.zeros_like(x)
            dx[idx] = eps
            fd[idx] = (f(x + dx) - f(x - dx)) / (2 * eps)
    assert grad.abs().max() > 1e-3
    torch.testing.assert_close(grad, fd, rtol=1e-4, atol=1e-7)


def test_device_and_dtype_follow_the_input(body, model):
    pose = torch.as_tensor(crossing_poses(), dtype=torch.float32)
    e = frame_energies(model, body.joint_transforms(pose, torch.zeros(10)))
    assert e.dtype == torch.float32 and e.device == pose.device
    np.testing.assert_allclose(e.numpy(), energies(body, model, crossing_poses()), rtol=1e-3,
                               atol=1e-7)


def test_allow_pairs_and_group_names(body):
    assert group_name("left_index2") == "left_hand" and group_name("right_wrist") == "right_hand"
    pose = crossing_poses()[2:3]
    base = collision_model(body, vertex_stride=4)
    allowed = collision_model(body, vertex_stride=4,
                              allow_pairs=[("left_hand", "spine3"), ("right_hand", "spine3"),
                                           ("left_elbow", "spine3"), ("right_elbow", "spine3"),
                                           ("left_hand", "right_hand"),
                                           ("left_elbow", "right_elbow"),
                                           ("left_hand", "right_elbow"),
                                           ("right_hand", "left_elbow")])
    assert energies(body, base, pose)[0] > 0
    assert energies(body, allowed, pose)[0] < energies(body, base, pose)[0]
    with pytest.raises(ConfigError, match="allow_pairs"):
        collision_model(body, allow_pairs=[("left_hand", "tail")])


def test_exclusions_cover_the_skeleton(body, model):
    groups = model.groups
    checked = checked_pairs(groups, body.joint_names, body.parents)
    idx = groups.index
    assert np.array_equal(checked, checked.T) and not checked.diagonal().any()
    # parent-child, through joints that own no vertices (collar): upper arm-chest excluded
    assert not checked[idx("left_shoulder"), idx("spine3")]
    assert not checked[idx("left_hand"), idx("left_elbow")]
    assert not checked[idx("left_hip"), idx("right_hip")]
    assert checked[idx("left_hand"), idx("head")] and checked[idx("left_hand"), idx("right_hand")]


def test_points_are_the_skinned_mesh(body, model):
    """Every mesh point sits on the skinned mesh (`body.vertices`), not on a rigid part, and the
    broad phase's per-frame chunk spheres contain all of them."""
    pose = torch.as_tensor(crossing_poses()[2:4], dtype=torch.float64)
    betas = torch.zeros(10, dtype=torch.float64)
    transforms = body.joint_transforms(pose, betas)
    pts = skinned_points(model, transforms)
    mesh = body.vertices(pose, betas)
    rest = body.rest_vertices(betas)
    mask = torch.as_tensor(model.chunk_mask)
    blended = mask & torch.as_tensor((model.chunk_weights < 1).all(-1))  # skinned by ≥2 joints
    assert blended.sum() > 100
    idx = torch.cdist(torch.as_tensor(model.chunk_points[blended.numpy()]), rest).argmin(1)
    torch.testing.assert_close(pts[:, blended], mesh[:, idx], rtol=0, atol=1e-6)
    d = model.tensors(torch.float64, torch.device("cpu"))
    center, radius = _chunk_spheres(d, _blend(d, transforms))
    dist = (pts - center[:, :, None]).norm(dim=-1)
    assert bool((dist[:, mask] <= radius[..., None].expand_as(dist)[:, mask]).all())


def test_refreshed_candidates_give_the_exact_energy(body, model):
    """The optimiser evaluates only the broad phase's point candidates between refreshes: at
    the refresh itself (same pose) that is the exact energy, for any margin and tolerance, and
    a pose moved by less than the margin keeps it exact too."""
    from embody.collision.energy import contacts
    pose = crossing_poses()
    betas = torch.zeros(10, dtype=torch.float64)
    tr = body.joint_transforms(torch.as_tensor(pose, dtype=torch.float64), betas)
    for margin in (0.0, 0.005, 0.022):
        near = contacts(model, tr, margin)
        assert near.points.t.numel() > 0
        for tol in (0.0, 0.001, -min(margin, 0.003)):
            assert torch.equal(frame_energies(model, tr, tol, near),
                               frame_energies(model, tr, tol))
    near = contacts(model, tr, 0.022)
    moved = body.joint_transforms(torch.as_tensor(pose + 0.002, dtype=torch.float64), betas)
    assert torch.equal(frame_energies(model, moved, 0.001, near),
                       frame_energies(model, moved, 0.001))


def test_energies_and_exact_from_one_narrow_phase(body, model):
    """The optimiser's refresh: the clearance energy (with its gradient) and the clear test
    from one selection are `frame_energies` at each tolerance, bit for bit; the exact one's
    tolerance may not be below the other's (its rows would not be a subset)."""
    from embody.collision.energy import contacts, frame_energies_and_exact
    pose = crossing_poses()
    betas = torch.zeros(10, dtype=torch.float64)
    p = torch.tensor(pose, dtype=torch.float64, requires_grad=True)
    tr = body.joint_transforms(p, betas)
    near = contacts(model, tr.detach(), 0.022)
    e, exact = frame_energies_and_exact(model, tr, -0.002, 0.001, near)
    assert torch.equal(exact, frame_energies(model, tr.detach(), 0.001))
    ref = frame_energies(model, tr, -0.002, near)
    assert torch.equal(e, ref) and exact.gt(0).any() and not exact.requires_grad
    g, = torch.autograd.grad(e.sum(), p, retain_graph=True)
    g_ref, = torch.autograd.grad(ref.sum(), p)
    assert torch.equal(g, g_ref)
    free = body.joint_transforms(torch.zeros(2, 55, 3, dtype=torch.float64), betas)
    e0, x0 = frame_energies_and_exact(model, free, -0.002, 0.001, contacts(model, free, 0.022))
    assert torch.equal(x0, torch.zeros(2)) and torch.equal(e0, frame_energies(model, free, -0.002))
    with pytest.raises(ValueError):
        frame_energies_and_exact(model, tr, 0.001, 0.0, near)
