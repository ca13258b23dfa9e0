"""Mesh penetration depth (the independent judge) on built cases, and the optimiser judged by it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from embody.body import MannequinBody
from embody.collision import mitigate
from embody.collision.depth import (DepthMesh, depth_metrics, frame_depth,
                                   frame_depth_reference, motion_depths)
from embody.collision.optimize import blend_weights
from embody.config.collision import CollisionConfig
from embody.motion import JOINT_NAMES, Motion

J = JOINT_NAMES.index
BOTH = np.array([[False, True], [True, False]])


def sphere_and_box(dip: float, checked: np.ndarray = BOTH) -> tuple[DepthMesh, np.ndarray]:
    """A 5 cm sphere (vertex at its south pole) dipping `dip` into the top of a 20 cm box."""
    s = trimesh.creation.uv_sphere(radius=0.05, count=[16, 16])
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    sv = s.vertices + [0.0, 0.0, 0.1 + 0.05 - dip]
    v = np.concatenate([sv, box.vertices])
    f = np.concatenate([s.faces, box.faces + len(sv)])
    groups = np.r_[np.zeros(len(sv), int), np.ones(len(box.vertices), int)]
    return DepthMesh.build(f, groups, checked), v


@pytest.mark.parametrize("dip", [0.0005, 0.004, 0.02])
def test_sphere_in_box_depth_is_the_dip(dip):
    mesh, v = sphere_and_box(dip)
    assert all(c.solid for c in mesh.components)
    assert frame_depth(mesh, v) == pytest.approx(dip, abs=1e-9)
    assert frame_depth(mesh, v) == frame_depth_reference(mesh, v)


def test_clear_touching_and_unchecked_score_zero():
    mesh, v = sphere_and_box(-0.003)  # 3 mm above the box
    assert frame_depth(mesh, v) == 0.0
    mesh, v = sphere_and_box(0.02, checked=np.zeros((2, 2), dtype=bool))
    assert frame_depth(mesh, v) == 0.0


def test_depth_metrics_counts_and_medians():
    m = depth_metrics(np.array([0.0, 0.001, 0.003, 0.006]), np.zeros(4))
    assert m["frames_over_2mm_before"] == 2 and m["frames_over_5mm_before"] == 1
    assert m["max_depth_mm_before"] == pytest.approx(6.0)
    assert m["median_depth_mm_before"] == pytest.approx(3.0)
    assert m["max_depth_mm_after"] == 0.0 and m["median_depth_mm_after"] == 0.0


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


def test_rest_and_t_pose_have_no_depth(body):
    """The wooden mesh is 29 watertight segments; touching segments at joints are excluded
    pairs, so the rest (T-) pose and arms-down scores exactly 0."""
    down = np.zeros((1, 55, 3))
    down[0, J("left_shoulder"), 2] = -1.2
    down[0, J("right_shoulder"), 2] = 1.2
    pose = np.concatenate([np.zeros((1, 55, 3)), body.tpose(1).numpy(), down])
    np.testing.assert_array_equal(motion_depths(body, pose, np.zeros(10)), 0.0)


def planted(frames: int, hit: slice) -> Motion:
    """T-pose, with the left forearm planted in the chest on the `hit` frames."""
    pose = np.zeros((frames, 55, 3))
    pose[hit, J("left_shoulder")] = [0.0, -0.8, -0.3]
    pose[hit, J("left_elbow"), 1] = -2.2
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=30.0)


def test_planted_forearm_in_chest_comes_out_under_3mm(body):
    motion = planted(44, slice(20, 24))
    r = mitigate(motion, body, CollisionConfig())
    m = r.metrics
    assert m["max_depth_mm_before"] > 15.0 and m["frames_over_5mm_before"] == 4
    assert m["max_depth_mm_after"] < 3.0 and m["frames_over_5mm_after"] == 0
    after = motion_depths(body, r.motion.pose, motion.betas)
    assert after.max() * 1e3 == pytest.approx(m["max_depth_mm_after"])
    # frames more than the blend window (0.5 s = 15 frames) away are the input, bit for bit
    far = np.r_[0:5, 39:44]
    assert r.motion.pose[far].tobytes() == motion.pose[far].astype(r.motion.pose.dtype).tobytes()
    assert not np.array_equal(r.motion.pose[20:24], motion.pose[20:24])


def test_blend_weights_fade_smoothly_to_zero():
    w = blend_weights(np.r_[np.zeros(20, bool), np.ones(2, bool), np.zeros(20, bool)], 10)
    assert w[20] == w[21] == 1.0
    assert (w[:11] == 0).all() and (w[31:] == 0).all()
    assert np.all(np.diff(w[10:21]) > 0) and np.all(np.diff(w[21:32]) < 0)
    assert np.abs(np.diff(w, 2)).max() < 0.05  # no kinks: the ramp is a cosine


def test_forearms_passed_through_each_other_come_apart(body):
    """The synthetic set's crossed-hands artifact (seq_000, frames 64-87): the forearm axes
    cross (1-2 mm apart), where the point energy alone cancels and stalled at ~35 mm deep; the
    limb core capsules separate them, and the mesh judge measures the result."""
    from embody.collision.capsules import arm_capsules, capsule_energies
    from embody.synth import generate_sequence

    src = generate_sequence(0, 0)
    motion = Motion(pose=src.pose[64:88], transl=np.zeros((24, 3)), betas=src.betas, fps=src.fps)
    caps = arm_capsules(body, motion.betas)
    import torch
    with torch.no_grad():
        tr = body.joint_transforms(torch.as_tensor(motion.pose), torch.as_tensor(motion.betas))
        assert (capsule_energies(caps, tr) > 0).sum() >= 10  # the cores overlap: crossed
    r = mitigate(motion, body, CollisionConfig())
    m = r.metrics
    assert m["max_depth_mm_before"] > 30.0 and m["frames_over_5mm_before"] >= 15
    assert m["max_depth_mm_after"] < 3.0 and m["frames_over_5mm_after"] == 0
    stalled = mitigate(motion, body, CollisionConfig(capsule_weight=0.0, depth_metrics=False,
                                                     steps=150))
    after = motion_depths(body, stalled.motion.pose, motion.betas)
    assert after.max() > 0.01  # without the capsules the forearms stay crossed


def test_depth_polish_clears_the_frames_the_judge_flags_and_nothing_else(body):
    """`polish` re-optimises only frames the mesh judge finds deeper than `depth_polish`
    (every vertex, blended over `blend_s`); the rest stays the input bit for bit."""
    from embody.collision.masks import mask_joints
    from embody.collision.optimize import polish

    motion = planted(44, slice(20, 24))
    cfg = CollisionConfig()
    idx = mask_joints(cfg.mask, cfg.joints)
    depth = motion_depths(body, motion.pose, motion.betas)
    assert depth.max() > 0.015
    pose, steps, after = polish(body, motion, motion.pose, idx, depth, cfg)
    assert steps > 0 and after.max() <= cfg.depth_polish
    np.testing.assert_allclose(after, motion_depths(body, pose, motion.betas), atol=1e-9)
    far = np.r_[0:5, 39:44]
    assert pose[far].tobytes() == motion.pose[far].astype(pose.dtype).tobytes()
    # nothing deeper than the threshold: the pose comes back untouched
    same, none, d = polish(body, motion, motion.pose, idx, np.minimum(depth, 0.001), cfg)
    assert none == 0 and same is motion.pose


def test_batched_depths_equal_the_per_frame_reference(body):
    """`frame_depths` prunes component pairs whose boxes are apart and tests a separating
    axis before the crossing test; the depths equal the NumPy reference `frame_depth_reference`
    over every checked pair, on built and random poses."""
    import torch
    from embody.collision.depth import depth_mesh, frame_depth_reference, frame_depths
    rng = np.random.default_rng(0)
    pose = np.concatenate([planted(3, slice(1, 2)).pose,
                           rng.normal(scale=0.6, size=(4, 55, 3))])
    pose[:, :3] = 0.0  # pelvis and hips still: the random part is in the arms and spine
    mesh = depth_mesh(body)
    with torch.no_grad():
        v = body.vertices(torch.as_tensor(pose), torch.zeros(10, dtype=torch.float64)).numpy()
    ours = frame_depths(mesh, v)
    ref = np.array([frame_depth_reference(mesh, x) for x in v])
    np.testing.assert_array_equal(ours, ref)
    assert ours[1] > 0.01 and (ours > 0).sum() >= 2


def test_pull_back_shrinks_the_correction_and_keeps_frames_clear(body):
    """`pull_back` scales each frame's correction by s(t) ∈ [0, 1] (never away from the
    input), never leaves a frame deeper than `pull_back_depth` (or its depth before), lowers
    Pose MSE, and leaves uncorrected frames bit for bit."""
    from embody.collision.metrics import accel_mse, pose_mse
    from embody.collision.optimize import pull_back

    motion = planted(44, slice(20, 24))
    cfg = CollisionConfig()
    pose = mitigate(motion, body, cfg.model_copy(update={"pull_back": False})).motion.pose
    depth = motion_depths(body, pose, motion.betas)
    new, d = pull_back(body, motion, pose, depth, cfg)
    np.testing.assert_allclose(d, motion_depths(body, new, motion.betas), atol=1e-12)
    assert (d <= np.maximum(depth, cfg.pull_back_depth) + 1e-9).all()
    c0 = (pose - motion.pose).reshape(44, -1)
    c1 = (new - motion.pose).reshape(44, -1)
    n0 = (c0 ** 2).sum(1)
    s = (c0 * c1).sum(1) / np.where(n0 > 0, n0, 1.0)
    np.testing.assert_allclose(c1, s[:, None] * c0, atol=1e-6)  # along the correction
    assert (s >= 0).all() and (s <= 1 + 1e-9).all() and (s[n0 > 0] < 1).any()
    assert pose_mse(new, motion.pose) < 0.99 * pose_mse(pose, motion.pose)
    assert accel_mse(new) - accel_mse(motion.pose) <= 5.71e-3
    still = n0 == 0
    assert still.any() and new[still].tobytes() == pose[still].tobytes()
    off, d_off = pull_back(body, motion, pose, depth, cfg.model_copy(update={"pull_back": False}))
    assert off is pose and d_off is depth


def test_regula_falsi_finds_the_smallest_clear_fraction_in_few_judge_calls():
    """`_regula_falsi` (the pull-back's search) on depth curves shaped like the judge's
    (0 past the contact at s ≈ 0.97-0.995, then growing nearly linearly, as measured on the
    default sequences): the s it returns is never too deep, lies within the search tolerances of the true
    root, judges only unsettled frames, and takes fewer calls than the 6 of the bisection it
    replaced; frames already within the limit at s = 0 get 0. A far contact (s = 0.8) still
    ends clear within the iteration cap."""
    from embody.collision.optimize import _D_TOL, _S_TOL, _regula_falsi

    contact = np.array([0.99, 0.985, 0.975, 0.995, 0.98, 0.3])
    slope = np.array([0.13, 0.05, 0.3, 0.1, 0.13, 0.1])  # m per unit of s
    power = np.array([1.0, 1.2, 1.0, 1.0, 0.9, 1.0])
    limit = np.full(6, 0.001)

    def depth(f: np.ndarray, s: np.ndarray) -> np.ndarray:
        return slope[f] * np.clip(contact[f] - s, 0, None) ** power[f]

    calls: list[int] = []

    def judge(f: np.ndarray, s: np.ndarray) -> np.ndarray:
        calls.append(len(f))
        return depth(f, s)

    all_ = np.arange(6)
    d_lo = depth(all_, np.zeros(6))
    d_lo[5] = 0.0005  # within the limit at s = 0
    s = _regula_falsi(judge, d_lo, depth(all_, np.ones(6)), limit, 10)
    root = contact - (limit / slope) ** (1 / power)
    assert (depth(all_[:5], s[:5]) <= limit[:5] + 1e-15).all()
    assert s[5] == 0.0
    slack = s[:5] - root[:5]
    close = (slack <= _S_TOL + 1e-12) | (depth(all_[:5], s[:5]) >= limit[:5] - _D_TOL)
    assert (slack >= -1e-12).all() and close.all()
    assert len(calls) < 6 and calls == sorted(calls, reverse=True) and calls[0] == 5
    far = _regula_falsi(lambda f, s: 0.1 * np.clip(0.8 - s, 0, None), np.array([0.08]),
                        np.zeros(1), np.array([0.001]), 10)
    assert 0.79 <= far[0] < 1.0


def test_regula_falsi_steps_on_from_the_clear_side_instead_of_halving():
    """Where the first probes land on the flat, clear side of a contact well below s = 1 (roots
    near 0.92, as on the synthetic set), the search steps on from the clear end (twice its last
    move) rather than probing the middle of [0, s]: this frame settles in 3 judge calls, clear
    and within the tolerances of the root (a halving probed s ≈ 0.48 and took 5)."""
    from embody.collision.optimize import _D_TOL, _S_TOL, _regula_falsi

    contact, slope, limit = 0.93, 0.1, np.array([0.001])

    def depth(s: np.ndarray) -> np.ndarray:
        return slope * np.clip(contact - s, 0, None)

    probes: list[float] = []

    def judge(f: np.ndarray, s: np.ndarray) -> np.ndarray:
        probes.extend(s.tolist())
        return depth(s)

    s = _regula_falsi(judge, depth(np.zeros(1)), depth(np.ones(1)), limit, 5)
    root = contact - limit[0] / slope
    assert depth(s)[0] <= limit[0] and s[0] >= root - 1e-12
    assert s[0] - root <= _S_TOL or depth(s)[0] >= limit[0] - _D_TOL
    assert len(probes) <= 3 and min(probes) > 0.9
