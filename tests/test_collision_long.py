"""The collision step's cost follows the frames that need work: no optimiser steps on a clip
without collision, and the depth polish in independent chunks on long sequences."""

from __future__ import annotations

import numpy as np
import pytest

from embody.body import MannequinBody
from embody.collision.depth import motion_depths
from embody.collision.masks import mask_joints
from embody.collision.optimize import (blend_weights, mitigate, nearest_index, polish,
                                       polish_chunks)
from embody.collision.windows import mitigate_windowed
from embody.config.collision import CollisionConfig
from embody.motion import JOINT_NAMES, Motion
from embody.synth.idle import idle_motion

J = JOINT_NAMES.index


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


def planted(frames: int, hits: list[slice]) -> Motion:
    """T-pose, with the left forearm planted in the chest on the `hits` frames."""
    pose = np.zeros((frames, 55, 3))
    for hit in hits:
        pose[hit, J("left_shoulder")] = [0.0, -0.8, -0.3]
        pose[hit, J("left_elbow"), 1] = -2.2
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=30.0)


def test_a_clip_without_collision_runs_no_optimiser_step(body):
    motion = idle_motion(300, 120.0)
    r = mitigate_windowed(motion, body, CollisionConfig(window_frames=128))
    assert r.metrics["windows"] == 3
    assert r.metrics["steps"] == 0 and r.metrics["polish_steps"] == 0
    assert r.frame_energy_before.max() == 0.0 and r.metrics["max_depth_mm_before"] == 0.0
    assert r.motion.pose.tobytes() == motion.pose.astype(r.motion.pose.dtype).tobytes()
    one = mitigate(idle_motion(60, 120.0), body, CollisionConfig())
    assert one.metrics["steps"] == 0 and one.metrics["polish_steps"] == 0


def test_nearest_index_and_blend_weights_match_the_dense_distance():
    rng = np.random.default_rng(3)
    for _ in range(200):
        t = int(rng.integers(1, 80))
        pts = np.unique(rng.integers(0, t, int(rng.integers(1, 12))))
        frames = np.arange(t)
        dense = np.abs(frames[:, None] - pts[None, :])
        assert np.array_equal(nearest_index(pts, frames), dense.argmin(1))  # ties: the earlier
        pen = np.zeros(t, bool)
        pen[pts] = True
        d = dense.min(1)
        w = int(rng.integers(1, 10))
        ref = np.where(d < w, 0.5 * (1.0 + np.cos(np.pi * d / w)), 0.0)
        np.testing.assert_allclose(blend_weights(pen, w), ref, atol=0, rtol=0)


def test_polish_chunks_merge_runs_within_the_size():
    active = np.zeros(100, bool)
    active[5:20] = active[30:40] = active[80:90] = True
    assert polish_chunks(active, 500) == [(5, 90)]
    assert polish_chunks(active, 40) == [(5, 40), (80, 90)]
    assert polish_chunks(active, 16) == [(5, 20), (30, 40), (80, 90)]
    assert polish_chunks(np.zeros(10, bool), 16) == []


def test_chunked_polish_matches_the_whole_polish(body):
    """Two contacts 50 frames apart: polished in one piece (window 500) and in two chunks
    (window 40) both clear every frame to `depth_polish`, touch no frame outside the blend
    windows, and the poses agree within 0.05 rad."""
    motion = planted(100, [slice(20, 24), slice(70, 74)])
    idx = mask_joints("arms", [])
    depth = motion_depths(body, motion.pose, motion.betas)
    assert depth.max() > 0.015
    whole_cfg = CollisionConfig(window_frames=500)
    chunk_cfg = CollisionConfig(window_frames=40, window_overlap=10)
    assert polish_chunks(blend_weights(depth > whole_cfg.depth_polish, 15) > 0, 40) == \
        [(6, 38), (56, 88)]
    whole, n_whole, d_whole = polish(body, motion, motion.pose, idx, depth, whole_cfg)
    parts, n_parts, d_parts = polish(body, motion, motion.pose, idx, depth, chunk_cfg)
    assert n_whole > 0 and n_parts > 0
    for pose, d in ((whole, d_whole), (parts, d_parts)):
        assert d.max() <= whole_cfg.depth_polish
        np.testing.assert_allclose(d, motion_depths(body, pose, motion.betas), atol=1e-9)
        far = np.r_[0:6, 38:56, 88:100]
        assert pose[far].tobytes() == motion.pose[far].astype(pose.dtype).tobytes()
    assert np.abs(parts - whole).max() < 0.05
