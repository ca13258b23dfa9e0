"""Masked optimisation (Eq. 2–3): fewer collisions, frozen joints bit-identical, deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from embody.body import MannequinBody
from embody.collision import CollisionResult, collision_energy, mask_joints, mitigate
from embody.collision import frame_collision_energies
from embody.collision.masks import PRESETS, mask_vector
from embody.collision.optimize import energies_reusing
from embody.config.collision import CollisionConfig
from embody.errors import ConfigError
from embody.motion import JOINT_NAMES, Motion

J = JOINT_NAMES.index


def colliding_motion(frames: int = 12) -> Motion:
    """Forearms swinging through the chest, fingers curling."""
    s = np.linspace(0.0, 1.0, frames)
    pose = np.zeros((frames, 55, 3))
    pose[:, J("left_shoulder")] = np.stack([0 * s, -1.0 + 0 * s, -0.3 + 0 * s], 1)
    pose[:, J("right_shoulder")] = np.stack([0 * s, 1.0 + 0 * s, 0.3 + 0 * s], 1)
    pose[:, J("left_elbow"), 1] = -1.6 - 0.8 * s
    pose[:, J("right_elbow"), 1] = 1.6 + 0.8 * s
    pose[:, 25:40, 2] = -0.8 * s[:, None]
    pose[:, 40:55, 2] = 0.8 * s[:, None]
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=30.0)


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


@pytest.fixture(scope="module")
def fixed(body) -> CollisionResult:
    return mitigate(colliding_motion(), body, CollisionConfig(steps=150))


def test_reduces_the_energy(body, fixed):
    m = fixed.metrics
    assert m["energy_before"] > 1e-3 and not m["no_collision"]
    assert m["improved"] and m["reduction_pct"] >= 90.0
    assert m["energy_after"] == pytest.approx(collision_energy(fixed.motion, body), abs=1e-12)
    assert 0 < m["steps"] <= 150 and m["frames"] == 12 and m["pose_mse"] > 0
    np.testing.assert_allclose(fixed.frame_energy_before.mean(), m["energy_before"])


def test_energies_reused_for_unchanged_frames_are_the_full_evaluation(body, fixed):
    """`energies_reusing` (only changed frames evaluated) returns the full evaluation's bits,
    and the result's energies after are those of its pose."""
    motion, cfg = colliding_motion(), CollisionConfig()
    before = frame_collision_energies(motion, body, cfg)
    after = frame_collision_energies(fixed.motion, body, cfg)
    assert np.array_equal(fixed.frame_energy_after.view(np.uint64), after.view(np.uint64))
    mixed = motion.pose.copy()
    mixed[::3] = fixed.motion.pose[::3]  # some frames changed, the rest the input's
    full = frame_collision_energies(motion.with_pose(mixed), body, cfg)
    assert not np.array_equal(full, before) and not np.array_equal(full, after)
    for known_pose, known in ((motion.pose, before), (fixed.motion.pose, after)):
        reused = energies_reusing(motion, mixed, body, cfg, known_pose, known)
        assert np.array_equal(reused.view(np.uint64), full.view(np.uint64))
    same = energies_reusing(motion, motion.pose, body, cfg, motion.pose, before)
    assert np.array_equal(same, before) and same is not before


def test_unmasked_joints_are_bit_identical(body, fixed):
    x0 = colliding_motion().pose
    free = mask_joints("arms")
    frozen = np.setdiff1d(np.arange(55), free)
    assert np.array_equal(fixed.motion.pose[:, frozen].view(np.uint32),
                          x0[:, frozen].view(np.uint32))
    assert not np.array_equal(fixed.motion.pose[:, free], x0[:, free])
    assert np.array_equal(fixed.motion.transl, colliding_motion().transl)
    hands = mitigate(colliding_motion(6), body, CollisionConfig(mask="hands", steps=5))
    assert np.array_equal(hands.motion.pose[:, :25], colliding_motion(6).pose[:, :25])


def test_seeded_runs_are_identical(body):
    cfg = CollisionConfig(steps=8, early_stop=False)
    a = mitigate(colliding_motion(6), body, cfg)
    b = mitigate(colliding_motion(6), body, cfg)
    assert a.motion.pose.tobytes() == b.motion.pose.tobytes() and a.metrics["steps"] == 8


def test_no_collision_and_disabled_leave_the_motion(body):
    calm = Motion(pose=np.zeros((4, 55, 3)), transl=np.zeros((4, 3)), betas=np.zeros(10), fps=30)
    r = mitigate(calm, body)
    assert r.metrics["no_collision"] and r.metrics["steps"] == 0 and r.metrics["reduction_pct"] == 0
    assert np.array_equal(r.motion.pose, calm.pose)
    off = mitigate(colliding_motion(4), body, CollisionConfig(enabled=False))
    assert off.metrics["steps"] == 0 and np.array_equal(off.motion.pose, colliding_motion(4).pose)


def test_result_round_trips_through_arrays(fixed):
    import json

    attrs = json.loads(json.dumps(fixed.to_attrs()))
    back = CollisionResult.from_arrays(fixed.to_arrays(), attrs)
    assert np.array_equal(back.motion.pose, fixed.motion.pose)
    assert back.metrics == fixed.metrics
    assert np.array_equal(back.frame_energy_after, fixed.frame_energy_after)


def test_mask_presets():
    assert len(mask_joints("hands")) == 30 and set(mask_joints("hands")) == set(range(25, 55))
    assert set(mask_joints("hands_wrists")) == set(range(25, 55)) | {20, 21}
    assert set(mask_joints("arms")) == set(range(25, 55)) | {13, 14, 16, 17, 18, 19, 20, 21}
    assert set(mask_joints("upper_body")) > set(mask_joints("arms"))
    assert list(mask_joints("joints", ["right_elbow", "neck"])) == [12, 19]
    assert mask_vector("hands").sum() == 30 and set(PRESETS) >= {"hands", "arms"}
    with pytest.raises(ConfigError, match="collision.joints"):
        mask_joints("joints", ["elbow"])
    with pytest.raises(ConfigError):
        mask_joints("joints", [])


def test_frame_adam_steps_along_each_frames_gradient():
    """The shared per-frame second moment keeps the gradient's direction within a frame (its
    RMS step is lr), where torch's Adam takes a sign-like step of lr on every parameter."""
    import torch

    from embody.collision.optimize import _FrameAdam

    g = torch.tensor([[[3.0, 0.0, 0.0], [0.0, 0.3, 0.0]], [[1e-3, 2e-3, 0.0], [0.0, 0.0, 0.0]]])
    u = torch.zeros_like(g, requires_grad=True)
    opt = _FrameAdam(u, lr=0.1)
    u.grad = g.clone()
    opt.step()
    rms = g.pow(2).mean(dim=(1, 2), keepdim=True).sqrt()
    torch.testing.assert_close(u.detach(), -0.1 * g / rms, rtol=1e-4, atol=1e-6)  # eps 1e-8
    ref = torch.zeros_like(g, requires_grad=True)
    adam = torch.optim.Adam([ref], lr=0.1)
    ref.grad = g.clone()
    adam.step()
    assert ref[0, 1, 1].item() == pytest.approx(-0.1, rel=1e-4)  # torch: as far as the big one
    assert u[0, 1, 1].item() == pytest.approx(0.1 * u[0, 0, 0].item(), rel=1e-5)  # ours: 1/10


def test_paper_preset_keeps_torch_adam_at_a_constant_step():
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[1]
    overlay = yaml.safe_load((root / "configs/collision/paper.yaml").read_text())["collision"]
    cfg = CollisionConfig.model_validate({**CollisionConfig().model_dump(), **overlay})
    assert cfg.adam_norm == "parameter" and cfg.lr_decay == 1.0 and cfg.lr == 0.01
    assert CollisionConfig().adam_norm == "frame"
