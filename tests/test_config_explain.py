"""`embody config --explain`: every key is either one a user sets (with a meaning and unit) or
internal tuning (with its source comment), and the user list names only real keys."""

from __future__ import annotations

import json
import re

from click.testing import CliRunner

from embody.cli import cli
from embody.config import Config
from embody.config.explain import TUNING_NOTES, USER_KEYS, config_keys, describe

UNIT = re.compile(r"\((?:[^()]*)\)$")


def test_user_and_tuning_keys_are_real_keys():
    keys = set(config_keys())
    assert set(USER_KEYS) <= keys, sorted(set(USER_KEYS) - keys)
    assert set(TUNING_NOTES) <= keys - set(USER_KEYS), sorted(set(TUNING_NOTES) - keys)


def test_every_user_key_has_one_line_with_a_unit():
    for key, line in USER_KEYS.items():
        assert "\n" not in line and len(line) <= 120, key
        assert UNIT.search(line), f"{key}: no (unit) at the end of {line!r}"


def test_every_key_is_described():
    missing = [k for k in config_keys() if not describe(k) or describe(k).startswith("see ")]
    assert not missing, f"keys without a meaning in --explain: {missing}"


def test_explain_lists_every_key_once_split_in_two():
    result = CliRunner().invoke(cli, ["config", "--explain", "--set", "ik.w_smooth=0.5"])
    assert result.exit_code == 0, result.output
    user_part, tuning_part = result.output.split("# Internal tuning")
    listed = re.findall(r"(?m)^([a-z_]+(?:\.[a-z_]+)+)\s", result.output)
    assert sorted(listed) == sorted(config_keys(Config()))
    assert re.search(r"(?m)^ik\.w_smooth\s+0\.5\s", user_part)
    assert re.search(r"(?m)^collision\.lr\s", tuning_part)
    assert not re.search(r"(?m)^collision\.lr\s", user_part)


def test_explain_json_has_both_groups():
    result = CliRunner().invoke(cli, ["config", "--explain", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert set(data["user"]) == set(USER_KEYS)
    assert set(data["user"]) | set(data["tuning"]) == set(config_keys())
