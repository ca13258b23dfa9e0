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
