"""Limb core capsules: exact segment distance, and cores that overlap only where skins do."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.body import MannequinBody
from embody.collision.capsules import arm_capsules, capsule_energies, segment_distance
from embody.collision.depth import motion_depths
from embody.synth import generate_sequence


def brute(p1, q1, p2, q2) -> float:
    s = np.linspace(0, 1, 801)
    a = p1 + np.outer(s, q1 - p1)
    b = p2 + np.outer(s, q2 - p2)
    return float(np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min())


def test_segment_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    cases = [np.array([[0, 0, 0], [1, 0, 0], [0.5, -1, 0.2], [0.5, 1, 0.2]], float),  # crossing
             np.array([[0, 0, 0], [1, 0, 0], [2, 0.3, 0], [3, 0.3, 0]], float),       # end to end
             np.array([[0, 0, 0], [1, 0, 0], [0.2, 0.1, 0], [0.8, 0.1, 0]], float)]   # parallel
    cases += list(rng.normal(size=(20, 4, 3)))
    for c in cases:
        d = segment_distance(*torch.as_tensor(c))
        assert float(d) == pytest.approx(brute(*c), abs=2e-3)
    p = torch.tensor(cases[0], requires_grad=True)
    segment_distance(*p).backward()
    # crossing 0.2 apart: the distance grows by moving the segments apart along z
    assert p.grad[:2, 2].sum() < 0 < p.grad[2:, 2].sum()


def test_cores_overlap_only_where_the_skin_is_deep():
    body = MannequinBody()
    src = generate_sequence(0, 0)
    pose = src.pose[::4]
    caps = arm_capsules(body, src.betas)
    assert len(caps.reach) == 9  # left × right: upper arm, forearm, palm
    with torch.no_grad():
        e = capsule_energies(caps, body.joint_transforms(torch.as_tensor(pose),
                                                         torch.as_tensor(src.betas))).numpy()
    hit = np.flatnonzero(e > 0)
    assert len(hit) >= 3  # the crossed forearms (frames 68-85)
    depth = motion_depths(body, pose[hit], src.betas)
    assert (depth > 0.02).all()  # cores are thinner than the skin: overlap means deep


@pytest.mark.parametrize("margin", [0.0, 0.01])
def test_compiled_capsule_energies_match_the_tensor_ones(margin):
    """Values and gradients (float64) equal autograd's through `segment_closest`, on crossed
    arms (overlapping cores) and random arm poses; gradcheck on the compiled one."""
    from test_collision_compiled import crossing_poses
    body = MannequinBody()
    caps = arm_capsules(body, np.zeros(10))
    pose = torch.as_tensor(crossing_poses())
    tr = body.joint_transforms(pose, torch.zeros(10, dtype=torch.float64)).detach()
    a = tr.clone().requires_grad_(True)
    b = tr.clone().requires_grad_(True)
    ea = capsule_energies(caps, a, margin)
    eb = capsule_energies(caps, b, margin, compiled=True)
    assert (ea > 0).sum() >= 3
    torch.testing.assert_close(eb, ea, rtol=1e-10, atol=1e-14)
    w = torch.linspace(0.5, 2.0, len(ea), dtype=torch.float64)
    (ea * w).sum().backward()
    (eb * w).sum().backward()
    assert a.grad.abs().max() > 0
    torch.testing.assert_close(b.grad, a.grad, rtol=1e-8, atol=1e-12)
    frames = torch.nonzero(ea > 0).squeeze(1)[:2]
    x = tr[frames].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: capsule_energies(caps, t, margin, compiled=True),
                                    (x,), eps=1e-7, atol=1e-6)
