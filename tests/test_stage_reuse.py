"""Nothing computed twice: the refine step keeps its chosen round's control-rate array (exactly
what the metrics step would recompute), and steps share the retarget step's targets."""

import dataclasses
import json

import numpy as np
import pytest

from embody.config import Config
from embody.config.critic import CriticConfig
from embody.critic import RefineResult, refine
from embody.retarget import build_targets, solve
from embody.retarget.control import control_trajectory
from embody.tasks.pipeline import Context

from test_refine import FPS, IK, RENDER, _motion, _reachable_targets, robot  # noqa: F401


def test_refine_keeps_the_chosen_rounds_control_array(robot):  # noqa: F811
    reference = _reachable_targets(robot, 10)
    planted = reference.wrist_pos.copy()
    planted[:, 0, 2] += 0.10
    ik_targets = dataclasses.replace(reference, wrist_pos=planted)
    ik_only = solve(robot, ik_targets, IK)
    result = refine(_motion(10), None, None, robot, reference, ik_only, CriticConfig(rounds=2), IK,
                    RENDER, ik_targets=ik_targets)
    final = result.final
    assert final.index > 0  # a re-solved round is the result
    expected = control_trajectory(robot, final.q, FPS, IK.control_rate_hz, IK.contact_repair)
    assert np.array_equal(final.q_control, expected)
    assert all(r.q_control is None for r in result.rounds if r is not final)
    back = RefineResult.from_arrays(result.to_arrays(), json.loads(json.dumps(result.to_attrs())))
    assert np.array_equal(back.final.q_control, expected)


def test_targets_are_built_once_per_content(tmp_path):
    from embody.retarget import shape_fit
    from embody.tasks.stages import _targets
    ctx = Context(cfg=Config(), store_root=str(tmp_path), run="t")
    fit = shape_fit(ctx.robot, ctx.body, ctx.cfg.ik)
    motion = _motion(8)
    first = _targets(ctx, motion, fit, ctx.cfg.ik)
    assert _targets(ctx, motion, fit, ctx.cfg.ik) is first  # the retarget step's, reused
    rebuilt = build_targets(motion, ctx.body, fit, ctx.robot, ctx.cfg.ik)
    assert np.array_equal(first.wrist_pos, rebuilt.wrist_pos)
    plain = ctx.cfg.ik.model_copy(update={"location_preserving": False})
    assert _targets(ctx, motion, fit, plain) is not first  # another config, other targets
    moved = motion.with_pose(motion.pose + np.float32(0.01))
    other = _targets(ctx, moved, fit, ctx.cfg.ik)
    assert other is not first and not np.array_equal(other.wrist_pos, first.wrist_pos)


def test_baseline_targets_leave_the_memo_alone(tmp_path):
    """The metrics step's IK-only baseline targets (asked for once) are built without entering
    the memo, so they never push out the targets the retarget step built for a later step."""
    from embody.retarget import shape_fit
    from embody.tasks.stages import _TARGETS, _targets
    ctx = Context(cfg=Config(), store_root=str(tmp_path), run="t")
    fit = shape_fit(ctx.robot, ctx.body, ctx.cfg.ik)
    motion = _motion(8)
    _TARGETS.clear()  # as in a fresh worker: no earlier test's targets
    first = _targets(ctx, motion, fit, ctx.cfg.ik)
    held = dict(_TARGETS)
    plain = ctx.cfg.ik.model_copy(update={"location_preserving": False})
    baseline = _targets(ctx, motion, fit, plain, remember=False)
    assert dict(_TARGETS) == held  # nothing added, nothing evicted
    assert _targets(ctx, motion, fit, plain, remember=False) is not baseline  # built afresh
    rebuilt = build_targets(motion, ctx.body, fit, ctx.robot, plain)
    assert np.array_equal(baseline.wrist_pos, rebuilt.wrist_pos)
    assert _targets(ctx, motion, fit, ctx.cfg.ik) is first


def test_targets_memo_holds_every_sequence_a_run_has_in_flight():
    """The driver keeps 2 × workers batches in flight: the memo holds their targets (at least 32)."""
    from embody.tasks.stages import _targets_size
    assert _targets_size(Config.model_validate({"run": {"workers": 4, "batch_size": 10}})) == 80
    assert _targets_size(Config()) == 32
