"""The metrics step reuses the MuJoCo counts the IK's solve already made of its own arrays: the
reused numbers equal a fresh count, and a different array is counted afresh."""

import numpy as np

from embody.retarget import solve
from embody.retarget.validation import validation_counts
from embody.tasks.stages import _control_counts

from test_refine import FPS, IK, _reachable_targets, robot  # noqa: F401


def test_control_counts_reused_only_for_the_iks_own_array(robot):  # noqa: F811
    ik = solve(robot, _reachable_targets(robot, 10), IK)
    fresh = validation_counts(robot, ik.q_control, ik.control_rate_hz)
    assert _control_counts(ik, np.array(ik.q_control)) == fresh
    source = validation_counts(robot, ik.q, FPS, ik.frame_metrics["self_contacts"])
    assert source == validation_counts(robot, ik.q, FPS)  # the solve's contacts are MuJoCo's
    moved = ik.q_control.copy()
    moved[3, 0] += 1e-3
    assert _control_counts(ik, moved) is None  # another array: counted afresh by the caller
    assert _control_counts(ik, ik.q_control[:-1]) is None


def test_refine_stores_each_rounds_wrists_for_the_report_tracks(robot):  # noqa: F811
    import dataclasses
    import json

    from embody.config.critic import CriticConfig
    from embody.critic import RefineResult, refine
    from embody.critic.refine import robot_wrists

    from test_refine import RENDER, _motion

    reference = _reachable_targets(robot, 10)
    planted = reference.wrist_pos.copy()
    planted[:, 1, 2] += 0.10
    ik_targets = dataclasses.replace(reference, wrist_pos=planted)
    result = refine(_motion(10), None, None, robot, reference, solve(robot, ik_targets, IK),
                    CriticConfig(rounds=1), IK, RENDER, ik_targets=ik_targets)
    assert len(result.rounds) == 2
    back = RefineResult.from_arrays(result.to_arrays(), json.loads(json.dumps(result.to_attrs())))
    for r in back.rounds:  # what a fresh FK of the round's q gives, after the store round trip
        np.testing.assert_allclose(r.wrist_pos, robot_wrists(robot, r.q)[0], atol=1e-12)
    assert not np.allclose(back.rounds[0].wrist_pos, back.rounds[1].wrist_pos)
