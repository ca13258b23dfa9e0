"""Windowed mitigation of long sequences: covered spans, collisions still reduced, frozen joints
bit-identical, scores exact on the cross-faded frames."""

from __future__ import annotations

import numpy as np
import pytest

from embody.body import MannequinBody
from embody.collision import frame_collision_energies, mask_joints
from embody.collision.windows import mitigate_windowed, windows
from embody.config.collision import CollisionConfig
from embody.errors import ConfigError
from embody.config import load_config
from tests.test_collision_optimize import colliding_motion


@pytest.mark.parametrize("frames,size,overlap", [(10, 16, 4), (40, 16, 4), (41, 16, 4),
                                                 (20_000, 1000, 50), (1001, 1000, 50)])
def test_windows_cover_every_frame_with_the_overlap(frames, size, overlap):
    spans = windows(frames, size, overlap)
    assert spans[0][0] == 0 and spans[-1][1] == frames
    for (a0, a1), (b0, b1) in zip(spans, spans[1:]):
        assert a1 - b0 == overlap and b0 > a0
    assert all(2 <= e - s <= size + overlap + 1 for s, e in spans)


def test_long_motion_is_mitigated_in_windows(tmp_path):
    body = MannequinBody()
    motion = colliding_motion(30)
    cfg = CollisionConfig(steps=40, window_frames=16, window_overlap=4)
    res = mitigate_windowed(motion, body, cfg)
    m = res.metrics
    assert m["windows"] == 3 and m["frames"] == 30 and res.motion.num_frames == 30
    assert m["improved"] and m["reduction_pct"] >= 80.0
    # energies reported are the true ones of the returned motion, frame by frame
    np.testing.assert_allclose(res.frame_energy_after,
                               frame_collision_energies(res.motion, body, cfg), atol=1e-12)
    np.testing.assert_allclose(res.frame_energy_before,
                               frame_collision_energies(motion, body, cfg), atol=1e-12)
    # the mesh judge scores the blended whole (windows used to drop the depth rows)
    from embody.collision.depth import motion_depths
    after = motion_depths(body, res.motion.pose, motion.betas)
    assert m["max_depth_mm_after"] == pytest.approx(after.max() * 1e3)
    assert m["max_depth_mm_before"] > m["max_depth_mm_after"] and m["depth_s"] > 0
    frozen = np.setdiff1d(np.arange(55), mask_joints(cfg.mask))
    np.testing.assert_array_equal(res.motion.pose[:, frozen], motion.pose[:, frozen])


def test_window_config_is_checked():
    with pytest.raises(ConfigError, match="window_overlap"):
        load_config(sets=["collision.window_frames=40", "collision.window_overlap=30"])
    assert CollisionConfig().window_frames == 500


def test_long_ik_is_solved_in_windows_and_still_tracks():
    from embody.config.ik import IKConfig
    from embody.retarget.windows import solve_windowed
    from embody.robot import load_robot
    from tests.test_retarget_ik import _smooth_random_q, _targets_from_q

    robot = load_robot()
    targets = _targets_from_q(robot, _smooth_random_q(robot, 40, seed=3))
    sol = solve_windowed(robot, targets, IKConfig(window_frames=16, window_overlap=4))
    assert sol.metrics["windows"] == 3 and sol.q.shape == (40, robot.n_joints)
    # measured against the trajectory the targets came from, on every frame incl. the blends
    assert sol.metrics["wrist_pos_err_max_mm"] < 10.0
    assert np.all(sol.q >= robot.lower) and np.all(sol.q <= robot.upper)
    assert sol.metrics["velocity_violations"] == 0
    assert sol.metrics["self_collision_frames"] == 0  # the cross-fades are contact-repaired too


def test_the_public_solver_is_the_windowed_one():
    """`embody.retarget.solve` (what the retarget step, the critic's re-solves and the fidelity
    baseline call) windows long sequences, so none of them holds a whole long sequence's
    Jacobians at once."""
    import embody.retarget
    from embody.retarget.windows import solve_windowed

    assert embody.retarget.solve is solve_windowed
