"""`embody.clusters.median_cuts`: a deterministic partition into groups of at most `size`."""

from __future__ import annotations

import numpy as np

from embody.clusters import median_cuts


def test_median_cuts_partition_the_points_in_small_groups():
    pts = np.random.default_rng(0).normal(size=(101, 3)) * [5.0, 1.0, 0.2]
    groups = median_cuts(pts, 20)
    assert all(0 < len(g) <= 20 for g in groups)
    assert np.array_equal(np.sort(np.concatenate(groups)), np.arange(101))
    # the first cut is along the longest axis (x): every point of the first half lies left of
    # every point of the second
    half = len(groups) // 2
    left, right = np.concatenate(groups[:half]), np.concatenate(groups[half:])
    assert len(left) == 50 and pts[left, 0].max() <= pts[right, 0].min()
    assert all(np.array_equal(a, b) for a, b in zip(groups, median_cuts(pts, 20)))


def test_small_sets_stay_whole():
    pts = np.zeros((5, 3))
    assert [g.tolist() for g in median_cuts(pts, 5)] == [[0, 1, 2, 3, 4]]
    assert median_cuts(np.zeros((0, 3)), 4)[0].tolist() == []
