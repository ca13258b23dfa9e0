"""Control primitives: exact torso-frame offsets, rotations, window blending; action parsing."""

import json

import numpy as np
import pytest

from embody.critic.action import ACTION_SCHEMA, Action, Limits
from embody.critic.primitives import (
    ORIENTATION_NAMES,
    POSITION_NAMES,
    Primitive,
    apply_primitives,
    window_weights,
)

T = 20


def _targets():
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(T, 2, 3))
    rot = np.tile(np.eye(3), (T, 2, 1, 1))
    return pos, rot


@pytest.mark.parametrize("name, side, delta", [
    ("move_left_up", 0, (0, 0, 1)), ("move_left_down", 0, (0, 0, -1)),
    ("move_left_forward", 0, (1, 0, 0)), ("move_left_back", 0, (-1, 0, 0)),
    ("move_left_in", 0, (0, -1, 0)), ("move_left_out", 0, (0, 1, 0)),
    ("move_right_up", 1, (0, 0, 1)), ("move_right_in", 1, (0, 1, 0)),
    ("move_right_out", 1, (0, -1, 0)), ("move_right_back", 1, (-1, 0, 0)),
])
def test_position_primitives_offset_exactly_along_torso_axes(name, side, delta):
    pos, rot = _targets()
    new_pos, new_rot = apply_primitives(pos, rot, [Primitive(name, 0.1)], blend_frames=3)
    expected = pos.copy()
    expected[:, side] += 0.1 * np.asarray(delta, dtype=float)
    np.testing.assert_allclose(new_pos, expected, atol=1e-12)
    np.testing.assert_array_equal(new_rot, rot)  # positions only


@pytest.mark.parametrize("name, side, axis, moved, to", [
    # the hand's forward axis (x) turns toward the midline / up; the top (z) toward the midline
    ("left_yaw_in", 0, "z", 0, (0, -1, 0)), ("right_yaw_in", 1, "z", 0, (0, 1, 0)),
    ("left_yaw_out", 0, "z", 0, (0, 1, 0)), ("right_yaw_out", 1, "z", 0, (0, -1, 0)),
    ("left_pitch_up", 0, "y", 0, (0, 0, 1)), ("right_pitch_down", 1, "y", 0, (0, 0, -1)),
    ("left_roll_in", 0, "x", 2, (0, -1, 0)), ("right_roll_in", 1, "x", 2, (0, 1, 0)),
])
def test_orientation_primitives_turn_the_named_way(name, side, axis, moved, to):
    pos, rot = _targets()
    _, new_rot = apply_primitives(pos, rot, [Primitive(name, 90.0)], blend_frames=0)
    np.testing.assert_allclose(new_rot[:, side, :, moved], np.tile(to, (T, 1)), atol=1e-12)
    np.testing.assert_array_equal(new_rot[:, 1 - side], rot[:, 1 - side])
    # a 20° turn is a rotation by exactly 20° about a torso axis
    _, r20 = apply_primitives(pos, rot, [Primitive(name, 20.0)], blend_frames=0)
    cos = (np.trace(r20[0, side]) - 1) / 2
    assert np.degrees(np.arccos(cos)) == pytest.approx(20.0)


def test_window_is_full_inside_and_ramps_smoothly_outside():
    w = window_weights(30, (10, 15), blend_frames=4)
    assert np.all(w[10:16] == 1.0)
    assert np.all(w[:5] == 0.0) and np.all(w[21:] == 0.0)
    assert np.all(np.diff(w[5:11]) > 0) and np.all(np.diff(w[15:21]) < 0)  # monotone ramps
    np.testing.assert_allclose(w[5:10], w[20:15:-1])  # symmetric
    assert np.all(window_weights(30, None, 4) == 1.0)
    hard = window_weights(30, (10, 15), 0)
    assert hard.sum() == 6

    pos, rot = _targets()
    new_pos, _ = apply_primitives(pos, rot, [Primitive("move_right_up", 0.05, (5, 8))], blend_frames=2)
    dz = new_pos[:, 1, 2] - pos[:, 1, 2]
    np.testing.assert_allclose(dz[5:9], 0.05)
    assert 0 < dz[4] < 0.05 and 0 < dz[9] < 0.05
    assert np.all(dz[:2] == 0) and np.all(dz[12:] == 0)
    np.testing.assert_array_equal(new_pos[:, 0], pos[:, 0])


def test_offsets_accumulate_and_cancel():
    pos, rot = _targets()
    p1, r1 = apply_primitives(pos, rot, [Primitive("move_left_up", 0.1), Primitive("left_yaw_in", 20)], 0)
    p2, r2 = apply_primitives(p1, r1, [Primitive("move_left_down", 0.1), Primitive("left_yaw_out", 20)], 0)
    np.testing.assert_allclose(p2, pos, atol=1e-12)
    np.testing.assert_allclose(r2, rot, atol=1e-12)


LIMITS = Limits(num_frames=T)


def test_parse_strings_and_objects_with_defaults():
    reply = {"primitives_positions": ["move_left_up",
                                      {"name": "move_right_in", "amount": 0.05, "window": [2, 40]}],
             "primitives_orientation": [{"name": "left_yaw_in", "amount": None, "window": None}],
             "verdict": "revise", "reason": "left hand too low"}
    action = Action.parse(json.dumps(reply), LIMITS)
    assert action.valid and not action.accepted
    assert action.primitives == (Primitive("move_left_up", 0.10), Primitive("move_right_in", 0.05, (2, T - 1)),
                                 Primitive("left_yaw_in", 20.0))
    back = Action.from_json(action.to_json())
    assert back.primitives == action.primitives and back.verdict == "revise"
    fenced = "```json\n" + json.dumps({**reply, "verdict": "accept"}) + "\n```"
    assert Action.parse(fenced, LIMITS).accepted


@pytest.mark.parametrize("reply, why", [
    ("{not json", "malformed JSON"),
    ('{"primitives_positions": ["move_left_sideways"], "primitives_orientation": [], '
     '"verdict": "revise", "reason": ""}', "schema"),
    ('{"primitives_positions": [], "primitives_orientation": [], "verdict": "maybe", "reason": ""}', "schema"),
    ('{"primitives_positions": [], "verdict": "accept", "reason": ""}', "schema"),
    ('{"primitives_positions": [{"name": "move_left_up", "amount": -1, "window": null}], '
     '"primitives_orientation": [], "verdict": "revise", "reason": ""}', "amount"),
    ('{"primitives_positions": [{"name": "move_left_up", "amount": null, "window": [9, 3]}], '
     '"primitives_orientation": [], "verdict": "revise", "reason": ""}', "window"),
    ('{"primitives_positions": [{"name": "move_left_up", "amount": null, "window": [50, 60]}], '
     '"primitives_orientation": [], "verdict": "revise", "reason": ""}', "outside frames"),
])
def test_bad_replies_become_no_action_with_a_reason(reply, why, caplog):
    action = Action.parse(reply, LIMITS)
    assert not action.valid and not action.accepted and action.primitives == ()
    assert why in action.error
    assert any("rejected" in r.getMessage() for r in caplog.records)


def test_schema_names_every_primitive_and_is_strict():
    props = ACTION_SCHEMA["properties"]
    assert set(ACTION_SCHEMA["required"]) == set(props)
    assert ACTION_SCHEMA["additionalProperties"] is False
    names = props["primitives_positions"]["items"]["anyOf"][0]["enum"]
    assert names == list(POSITION_NAMES) and len(names) == 12
    assert props["primitives_orientation"]["items"]["anyOf"][0]["enum"] == list(ORIENTATION_NAMES)
    assert len(ORIENTATION_NAMES) == 12
