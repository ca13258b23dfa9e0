"""The critic judges against what the robot can do:

- a move toward the chest is limited to the room the IK's clearance leaves the hand (a G1 right
  hand 3 cm before its chest, as the default run's seq_003 holds it); moves along or away stay;
- against the human, a yaw off the IK target alone neither rejects nor asks for a turn; a hand
  whose palm is off the human's gets the turn toward the human's palm;
- `critic.keep: best` keeps an accepted round when there is one;
- a valid revise without primitives ends the loop (the next round would critique the same robot).
"""

import numpy as np
import pytest

from embody.config.critic import CriticConfig
from embody.critic import refine
from embody.critic.action import Action, Limits
from embody.critic.base import Critic, CritiqueContext
from embody.critic.geometric import GeometricCritic
from embody.critic.primitives import Primitive, axis_angle_matrix
from embody.critic.reach import Reach
from embody.critic.refine import RoundRecord, _chosen_round
from embody.retarget import solve
from embody.robot import load_robot

from test_refine import IK, RENDER, _motion, _reachable_targets

#: G1 right arm and hand from the default run's seq_003, frame 55 (IK-only): the right hand
#: stands 3.0 cm before the chest, which the hand-chest clearance holds it at.
_AT_CHEST = {"right_shoulder_pitch_joint": 0.652, "right_shoulder_roll_joint": -0.094,
             "right_shoulder_yaw_joint": 0.123, "right_elbow_joint": 0.025,
             "right_wrist_roll_joint": -0.488, "right_wrist_pitch_joint": -1.017,
             "right_wrist_yaw_joint": -0.045, "right_hand_thumb_0_joint": -0.524,
             "right_hand_thumb_1_joint": -0.762, "right_hand_thumb_2_joint": -1.269,
             "right_hand_middle_0_joint": 1.518, "right_hand_middle_1_joint": 1.678}


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def test_a_move_toward_the_chest_is_limited_to_the_room_the_clearance_leaves(robot):
    q = robot.tpose.copy()[None]
    for name, value in _AT_CHEST.items():
        q[0, robot.joint_index(name)] = value
    reach = Reach(robot)
    dist, direction = reach.closest(q, np.array([0]), "right")
    d, n = float(dist[0, 1]), direction[0, 1]
    assert 0.015 < d < 0.045, d
    assert abs(np.linalg.norm(n) - 1.0) < 1e-9 and n[0] < -0.8  # the chest is behind the hand
    along = np.cross(n, [1.0, 0.0, 0.0])
    along /= np.linalg.norm(along)
    offset = np.zeros((1, 2, 3))
    offset[0, 1] = 0.05 * n + 0.02 * along  # 5 cm into the chest, 2 cm along it
    required = np.zeros((1, 2, 2))
    required[:, :, 1] = d - 0.01  # the IK keeps the hand 1 cm closer than it is
    fallback = np.zeros((1, 2, 3))
    out, blocked = reach.clamp(q, offset, required, 0.0, fallback)
    assert blocked[0, 1] and not blocked[0, 0]
    np.testing.assert_allclose(out[0, 1] @ n, 0.01, atol=1e-9)   # as far as the clearance allows
    np.testing.assert_allclose(out[0, 1] @ along, 0.02, atol=1e-9)  # the move along stays
    np.testing.assert_allclose(out[0, 0], 0.0)
    # away from the chest, or toward it within the room, nothing changes
    for move, req in ((-0.05 * n, d - 0.01), (0.5 * d * n, 0.0)):
        offset[0, 1] = move
        required[:, :, 1] = req
        out, blocked = reach.clamp(q, offset, required, 0.0, fallback)
        np.testing.assert_allclose(out, offset, atol=1e-12)
        assert not blocked.any()


def _human_context(yaw_deg: float, palm_right: float, ik_yaw_deg: float = 0.0) -> CritiqueContext:
    """The right hand's palm `palm_right` deg off the human's, and `yaw_deg` the turn toward the
    human's palm; its wrist `ik_yaw_deg` off the IK target about z."""
    t = 30
    pos = np.zeros((t, 2, 3))
    ref_rot = np.tile(np.eye(3), (t, 2, 1, 1))
    rot = ref_rot.copy()
    rot[:, 1] = axis_angle_matrix(np.array([0, 0, 1.0]), np.full(t, np.radians(ik_yaw_deg))) @ ref_rot[:, 1]
    hands = {"left": {"palm_deg": 3.0, "yaw_deg": 0.0}, "right": {"palm_deg": palm_right, "yaw_deg": yaw_deg}}
    return CritiqueContext(0, 30.0, 0.45, pos, ref_rot, pos, rot, Limits(t),
                           location_offset=np.zeros((t, 2, 3)), body_scale=0.24,
                           fidelity={"location_err": 0.05, "palm_deg": (3.0 + palm_right) / 2},
                           hand_fidelity=hands)


def test_against_the_human_a_yaw_turn_is_asked_only_where_the_palm_is_off():
    critic = GeometricCritic(CriticConfig())
    # the wrist is 20 deg off the IK target's yaw, the palm faces as the human's: accepted
    calm = critic.critique(_human_context(-15.0, 6.0, ik_yaw_deg=20.0))
    assert calm.accepted and calm.primitives == ()
    # the right palm 30 deg off the human's: the turn toward the human's (−15 deg about z,
    # outward for the right hand), whatever the IK target's yaw says
    off = critic.critique(_human_context(-15.0, 30.0, ik_yaw_deg=-20.0))
    assert off.verdict == "revise" and off.primitives == (Primitive("right_yaw_out", 15.0),)


def _round(index: int, score: float, verdict: str | None) -> RoundRecord:
    action = None if verdict is None else Action(verdict=verdict).to_json()
    return RoundRecord(index, np.zeros((1, 1)), np.zeros((1, 2, 3)), np.zeros((1, 2, 3, 3)),
                       {"fidelity_score": score, "wrist_mm_mean": 0.0}, action)


def test_keep_best_keeps_an_accepted_round_when_there_is_one():
    cfg = CriticConfig()
    # round 1 scores a hair better, but the critic accepted round 2
    rounds = [_round(0, 0.20, "revise"), _round(1, 0.181, "revise"), _round(2, 0.182, "accept")]
    assert _chosen_round(rounds, cfg) == 2
    # nothing accepted: the best score
    rounds[2] = _round(2, 0.182, "revise")
    assert _chosen_round(rounds, cfg) == 1
    assert _chosen_round(rounds, cfg.model_copy(update={"keep": "last"})) == 2


def test_a_revise_without_primitives_ends_the_loop(robot):
    class NothingToDo(Critic):
        def critique(self, context):
            return Action(verdict="revise", reason="palm off, no primitive can help")

    reference = _reachable_targets(robot, 6)
    result = refine(_motion(6), None, None, robot, reference, solve(robot, reference, IK),
                    CriticConfig(rounds=2), IK, RENDER, critic=NothingToDo())
    assert len(result.rounds) == 1 and not result.accepted


def test_the_vlm_prompt_says_where_a_hand_stands_at_its_clearance():
    from embody.critic.vlm import _fidelity_facts

    ctx = _human_context(0.0, 5.0)
    ctx.hand_fidelity = {}
    assert _fidelity_facts(ctx) == ""
    ctx.reach_blocked = np.zeros((30, 2), dtype=bool)
    ctx.reach_blocked[4:16, 1] = True
    text = _fidelity_facts(ctx)
    assert "In 12 frames the robot's right hand already stands at its clearance" in text
    assert "left hand" not in text
