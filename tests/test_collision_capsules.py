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
