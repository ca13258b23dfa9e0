"""configs/default.yaml is generated from the typed models; the two must agree."""

import yaml

from embody.config import Config, configs_dir, load_config


def test_default_yaml_matches_model_defaults():
    data = yaml.safe_load((configs_dir() / "default.yaml").read_text())
    assert data == Config().model_dump(mode="json")


def test_default_yaml_has_every_stage_section():
    data = yaml.safe_load((configs_dir() / "default.yaml").read_text())
    for section in ("body", "collision", "robot", "ik", "render", "critic", "run"):
        assert section in data, section


def test_loaded_default_equals_model_default():
    assert load_config() == Config()


def test_config_command_prints_model_defaults(capsys):
    from embody.cli import main

    assert main(["config", "--model-defaults", "--set", "ik.iterations=3"]) == 0
    assert yaml.safe_load(capsys.readouterr().out) == Config().model_dump(mode="json")
