"""The torque and ZMP retiming runs once per sequence, on the array that is exported: the critic's
re-solves make kinematic control-rate arrays, the chosen round's exported array is limited and
counted, and the critic's acceptance holds only if it also accepts that exported array."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from embody.config.critic import CriticConfig
from embody.critic import RefineResult, refine
from embody.critic.action import Action
from embody.critic.base import Critic
from embody.critic.refine import _at_frames
from embody.retarget import solve
from embody.retarget.control import control_trajectory
from embody.retarget.ik import exported_control, without_dynamics_limits
from embody.retarget.validation import validation_counts
from embody.tasks.stages import _refine_metrics

from test_refine import FPS, IK, RENDER, _motion, _reachable_targets, robot  # noqa: F401


def test_without_dynamics_limits_changes_only_the_control_array(robot):  # noqa: F811
    targets = _reachable_targets(robot, 10)
    plain = without_dynamics_limits(IK)
    assert IK.dynamics_limits and not plain.dynamics_limits
    assert without_dynamics_limits(plain) is plain
    kinematic = solve(robot, targets, plain)
    np.testing.assert_allclose(kinematic.q, solve(robot, targets, IK).q, atol=1e-9)
    expected = control_trajectory(robot, kinematic.q, FPS, IK.control_rate_hz, IK.contact_repair, limits=None)
    np.testing.assert_allclose(kinematic.q_control, expected, atol=1e-12)
    limited, _, _ = exported_control(robot, kinematic.q, FPS, IK)
    np.testing.assert_allclose(limited, control_trajectory(robot, kinematic.q, FPS, IK.control_rate_hz,
                                                           IK.contact_repair), atol=1e-12)


def test_chosen_rounds_export_is_limited_and_counted(robot):  # noqa: F811
    reference = _reachable_targets(robot, 10)
    planted = reference.wrist_pos.copy()
    planted[:, 0, 2] += 0.10
    ik_targets = dataclasses.replace(reference, wrist_pos=planted)
    ik_only = solve(robot, ik_targets, without_dynamics_limits(IK))  # as the pipeline's retarget step
    result = refine(_motion(10), None, None, robot, reference, ik_only, CriticConfig(rounds=2), IK,
                    RENDER, ik_targets=ik_targets)
    final = result.final
    assert final.index > 0
    expected = control_trajectory(robot, final.q, FPS, IK.control_rate_hz, IK.contact_repair)
    np.testing.assert_allclose(final.q_control, expected, atol=1e-12)
    kinematic = control_trajectory(robot, final.q, FPS, IK.control_rate_hz, IK.contact_repair, limits=None)
    np.testing.assert_allclose(final.q_kinematic, kinematic, atol=1e-12)
    back = RefineResult.from_arrays(result.to_arrays(), json.loads(json.dumps(result.to_attrs())))
    np.testing.assert_array_equal(back.final.q_kinematic, final.q_kinematic)
    # each exported sample's source time: increasing, one per sample, spanning the source
    assert len(final.source_time) == len(final.q_control)
    assert (np.diff(final.source_time) > 0).all() and final.source_time[0] == 0.0
    np.testing.assert_array_equal(back.final.source_time, final.source_time)
    counts = validation_counts(robot, final.q_control, IK.control_rate_hz)
    assert {k: final.metrics[f"control_{k}"] for k in counts} == counts
    assert all(r.q_control is None for r in result.rounds if r is not final)
    # the critic accepted the round and, judged again, its exported array
    assert final.accepted and result.export_accepted is True and result.accepted
    exported = result.export["metrics"]
    # the two judgements differ by no more than the torque/ZMP retiming moved the wrists at the
    # source frames (triangle inequality on the mean wrist error)
    from embody.critic.refine import robot_wrists
    moved = robot_wrists(robot, _at_frames(final.q_control, final.source_time, len(final.q), FPS))[0]
    moved_mm = 1000.0 * np.linalg.norm(moved - robot_wrists(robot, final.q)[0], axis=-1)
    gap = abs(exported["wrist_mm_mean"] - final.metrics["wrist_mm_mean"])
    assert gap <= moved_mm.mean() + 1e-6
    stored = _refine_metrics(result)
    assert stored["accepted"] is True and stored["export_accepted"] is True
    assert stored["export.wrist_mm_mean"] == exported["wrist_mm_mean"]


class _AcceptsOnce(Critic):
    """Accepts the first trajectory it is shown, rejects every later one."""

    needs_images = False

    def __init__(self) -> None:
        self.calls = 0

    def critique(self, context):
        self.calls += 1
        verdict = "accept" if self.calls == 1 else "revise"
        prims = [] if self.calls == 1 else ["move_left_up"]
        return Action.parse({"primitives_positions": prims, "primitives_orientation": [],
                             "verdict": verdict, "reason": f"call {self.calls}"}, context.limits)


def test_acceptance_describes_the_exported_array(robot):  # noqa: F811
    """A critic that accepts the round but not its exported array: the result is not accepted,
    and the store round trip keeps that verdict."""
    reference = _reachable_targets(robot, 10)
    ik_only = solve(robot, reference, without_dynamics_limits(IK))
    critic = _AcceptsOnce()
    result = refine(_motion(10), None, None, robot, reference, ik_only, CriticConfig(rounds=2), IK,
                    RENDER, critic=critic)
    assert critic.calls == 2  # the round, then its exported array
    assert len(result.rounds) == 1 and result.final.accepted
    assert result.export_accepted is False and not result.accepted
    assert _refine_metrics(result)["accepted"] is False
    back = RefineResult.from_arrays(result.to_arrays(), json.loads(json.dumps(result.to_attrs())))
    assert back.export_accepted is False and not back.accepted
    assert back.export["action"]["reason"] == "call 2"


def test_rejected_result_is_not_judged_again(robot):  # noqa: F811
    class Rejects(Critic):
        needs_images = False
        calls = 0

        def critique(self, context):
            Rejects.calls += 1
            return Action.parse({"primitives_positions": [], "primitives_orientation": [],
                                 "verdict": "revise", "reason": "no"}, context.limits)

    reference = _reachable_targets(robot, 10)
    result = refine(_motion(10), None, None, robot, reference,
                    solve(robot, reference, without_dynamics_limits(IK)), CriticConfig(rounds=1), IK,
                    RENDER, critic=Rejects())
    assert Rejects.calls == 1 and result.export == {} and result.export_accepted is None
    assert not result.accepted and "export_accepted" not in _refine_metrics(result)
    assert result.final.q_control is not None  # the export is made whatever the verdict


def test_exported_array_read_at_the_source_frames():
    rate, fps, t = 50.0, 30.0, 10
    n = int(np.floor((t - 1) / fps * rate + 1e-9)) + 1
    times = np.arange(n) / rate
    ramp = np.stack([times, 2.0 * times + 1.0], axis=1)
    view = _at_frames(ramp, times, t, fps)
    frames = np.minimum(np.arange(t) / fps, times[-1])
    np.testing.assert_allclose(view, np.stack([frames, 2.0 * frames + 1.0], axis=1), atol=1e-12)
    same = np.random.default_rng(0).normal(size=(t, 3))
    np.testing.assert_allclose(_at_frames(same, np.arange(t) / fps, t, fps), same, atol=1e-12)


def test_retimed_array_read_at_its_source_times():
    """A retimed export (three times slower over its middle): read at the source frames through
    its samples' source times, it gives the source's values, not the slowed array's."""
    rate, fps, t = 50.0, 25.0, 26
    source = np.r_[np.arange(0, 20) / rate, 20 / rate + np.arange(0, 60) / (3 * rate),
                   40 / rate + np.arange(0, 11) / rate]
    line = np.stack([source, 1.0 - source], axis=1)  # the path at those source times
    view = _at_frames(line, source, t, fps)
    frames = np.minimum(np.arange(t) / fps, source[-1])
    np.testing.assert_allclose(view, np.stack([frames, 1.0 - frames], axis=1), atol=1e-12)
    # read on the uniform grid instead, the slowed array lags the source
    lagging = _at_frames(line, np.arange(len(line)) / rate, t, fps)
    assert np.abs(lagging[:, 0] - frames).max() > 0.1


def test_pipeline_limits_the_exported_array_once(tmp_path):
    """The critic pipeline's steps: the retarget step's array is kinematic, the metrics step
    stores the refine step's exported array with counts equal to a fresh count, and scores the
    chosen round's kinematic array apart from the exported one."""
    from embody.collision import CollisionResult
    from embody.config import Config
    from embody.retarget import shape_fit
    from embody.tasks.pipeline import Context
    from embody.tasks.stages import (METRICS_REFINED, REFINE, RETARGET, RETARGET_BEFORE_CRITIC,
                                     default_pipeline)

    assert RETARGET_BEFORE_CRITIC in default_pipeline(critic=True).steps
    assert RETARGET in default_pipeline(critic=False).steps
    cfg = Config.model_validate({"ik": {"iterations": 20, "shape_iterations": 10},
                                 "critic": {"rounds": 1}})
    assert RETARGET_BEFORE_CRITIC.key(cfg, {"collide": "a", "shape_fit": "b"}) != \
        RETARGET.key(cfg, {"collide": "a", "shape_fit": "b"})
    ctx = Context(cfg=cfg, store_root=str(tmp_path), run="t")
    motion = _motion(8)
    inputs = {"collide": CollisionResult(motion, {}, np.zeros(8), np.zeros(8)),
              "shape_fit": shape_fit(ctx.robot, ctx.body, cfg.ik)}
    ik = inputs["retarget"] = RETARGET_BEFORE_CRITIC.compute(ctx, inputs)
    kinematic = control_trajectory(ctx.robot, ik.q, ik.fps, ik.control_rate_hz, True, limits=None)
    np.testing.assert_allclose(ik.q_control, kinematic, atol=1e-12)
    refined = inputs["refine"] = REFINE.compute(ctx, inputs)
    final = refined.final
    np.testing.assert_allclose(final.q_control, control_trajectory(
        ctx.robot, final.q, ik.fps, ik.control_rate_hz, True), atol=1e-12)
    out = METRICS_REFINED.compute(ctx, inputs)
    np.testing.assert_array_equal(out.arrays["q_control"], final.q_control)
    np.testing.assert_array_equal(out.arrays["source_time"], final.source_time)
    assert out.metrics["time_stretch_max"] >= 1.0 and out.metrics["duration_ratio"] >= 1.0
    fresh = validation_counts(ctx.robot, out.arrays["q_control"], ik.control_rate_hz)
    assert {k: out.metrics[k] for k in fresh} == fresh
    assert out.metrics["fidelity.final"] == "refined"
    for row in ("ik", "preserving", "refined_kinematic", "refined"):
        assert np.isfinite(out.metrics[f"fidelity.{row}.location_err"])
