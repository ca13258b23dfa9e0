"""Typed config: bad keys/types/ranges rejected naming the key (exit 2), files and --set
layered in order, canonical JSON stable under key order and float noise."""

from __future__ import annotations

import json

import pytest
import yaml

from embody.cli import main
from embody.config import Config, canonical_json, load_config
from embody.errors import ConfigError


@pytest.fixture(autouse=True)
def _model_defaults(tmp_path, monkeypatch):
    """Layering is tested against the model defaults, whatever configs/default.yaml holds
    (tests/test_default_config.py checks that the two agree)."""
    monkeypatch.setenv("EMBODY_CONFIGS", str(tmp_path / "no-configs"))


def _effective(capsys, *args) -> dict:
    assert main(["config", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("item,key", [
    ("body.no_such_key=1", "body.no_such_key"),      # unknown key
    ("nosuch.key=1", "nosuch"),                      # unknown section
    ("run.workers=abc", "run.workers"),              # wrong type
    ("run.seed=1.5", "run.seed"),                    # wrong type (fractional int)
    ("run.workers=0", "run.workers"),                # out of range (ge=1)
    ("run.workers=100000", "run.workers"),           # out of range (le=256)
    ("run.limit=0", "run.limit"),                    # optional, still range-checked
    ("run.runner=fibers", "run.runner"),             # not one of the choices
    ("body.gender=robot", "body.gender"),
    ("debug.fail_on=3", "debug.fail_on"),
])
def test_bad_values_exit_2_naming_the_key(capsys, item, key):
    assert main(["config", "--set", item]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"'{key}'" in err and captured.out == ""


@pytest.mark.parametrize("item", ["run.workers", "run=3", "=3"])
def test_malformed_set_exits_2(capsys, item):
    assert main(["config", "--set", item]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_library_raises_config_error_with_key():
    with pytest.raises(ConfigError) as err:
        load_config(sets=["run.workers=-1"])
    assert err.value.key == "run.workers"


def test_config_files_then_set_override_in_order(tmp_path, capsys):
    first = tmp_path / "a.yaml"
    second = tmp_path / "b.yaml"
    first.write_text(yaml.safe_dump({"run": {"workers": 4, "seed": 7}, "body": {"gender": "female"}}))
    second.write_text("run:\n  workers: 6\ncollision:\n")  # an empty section keeps its defaults
    cfg = _effective(capsys, "--config", str(first))
    assert cfg["run"]["workers"] == 4 and cfg["run"]["seed"] == 7 and cfg["body"]["gender"] == "female"
    cfg = _effective(capsys, "--config", str(first), "--config", str(second))
    assert cfg["run"]["workers"] == 6 and cfg["run"]["seed"] == 7       # later file wins, rest merged
    cfg = _effective(capsys, "--config", str(first), "--set", "run.workers=8")
    assert cfg["run"]["workers"] == 8                                   # --set wins over files
    default = _effective(capsys)
    assert default["run"]["workers"] == Config().run.workers            # files do not stick


@pytest.mark.parametrize("content", ["run: [1, 2", "- a\n- b\n", "run:\n  workers: zero\n",
                                     "robot_arm:\n  x: 1\n"])
def test_bad_config_file_exits_2(tmp_path, capsys, content):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    assert main(["config", "--config", str(path)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_missing_config_file_names_it(tmp_path, capsys):
    assert main(["config", "--config", str(tmp_path / "nope.yaml")]) == 2
    assert "nope.yaml" in capsys.readouterr().err


def test_canonical_json_stable_under_key_order_and_float_noise():
    a = {"b": 1, "a": {"y": 0.1 + 0.2, "x": [1.0, 2.5]}}
    b = {"a": {"x": [1, 2.5], "y": 0.3}, "b": 1.0}
    assert canonical_json(a) == canonical_json(b) == '{"a":{"x":[1,2.5],"y":0.3},"b":1}'
    assert canonical_json({"v": 0.3}) != canonical_json({"v": 0.3001})  # real changes still show


def test_section_json_is_what_keys_hash():
    base = Config()
    changed = load_config(sets=["run.workers=3"], defaults="/nonexistent/default.yaml")
    assert base.section_json("body") == changed.section_json("body")
    assert base.section_json("run") != changed.section_json("run")
    assert json.loads(changed.section_json("run"))["workers"] == 3


def test_models_are_frozen():
    cfg = Config()
    with pytest.raises(Exception):
        cfg.run.workers = 5  # type: ignore[misc]


def _alias_bomb(levels: int, width: int = 9) -> str:
    """`run.name: [&a [x]*9, &b [*a]*9, ...]`: a few hundred bytes, 9**levels nodes expanded."""
    items = [f"&l0 [{', '.join(['x'] * width)}]"]
    items += [f"&l{i} [{', '.join([f'*l{i - 1}'] * width)}]" for i in range(1, levels)]
    return f"run:\n  name: [{', '.join(items)}]\n"


@pytest.mark.parametrize("levels", [6, 10])  # 0.5 M nodes; 3.5 G nodes (GBs when expanded)
def test_alias_bomb_in_a_valid_key_is_refused_in_one_short_line(tmp_path, capsys, levels):
    path = tmp_path / "bomb.yaml"
    path.write_text(_alias_bomb(levels))
    assert len(path.read_bytes()) < 1000
    assert main(["config", "--config", str(path)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and len(err) < 300, err[:300]
    assert "bomb.yaml" in err and "nodes" in err and captured.out == ""


def test_alias_bomb_in_set_and_recursive_alias_are_refused(tmp_path, capsys):
    bomb = _alias_bomb(8).split("name: ", 1)[1].strip()
    assert main(["config", "--set", f"run.name={bomb}"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and len(err) < 300 and "'run.name'" in err
    path = tmp_path / "loop.yaml"
    path.write_text("run:\n  name: &a [1, *a]\n")
    assert main(["config", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "loop.yaml" in err and "contains it" in err


def test_plain_anchors_still_work_and_long_values_are_quoted_short(tmp_path, capsys):
    path = tmp_path / "anchors.yaml"
    path.write_text("run:\n  workers: &w 3\n  batch_size: *w\n")
    cfg = _effective(capsys, "--config", str(path))
    assert cfg["run"]["workers"] == 3 and cfg["run"]["batch_size"] == 3
    path = tmp_path / "long.yaml"  # no alias, 60k items: the error quotes a few of them
    path.write_text("run:\n  name: [" + ", ".join(["xy"] * 60_000) + "]\n")
    assert main(["config", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and len(err) < 400 and "'run.name'" in err, err[:400]
