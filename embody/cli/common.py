"""Options and helpers shared by the commands."""

from __future__ import annotations

import json
from typing import Any

import click

from embody.config import Config, load_config


def config_options(f):
    """`--config FILE` (repeatable) and `--set section.key=value` (repeatable)."""
    f = click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
                     help="Override one config value (repeatable).")(f)
    f = click.option("--config", "config_files", multiple=True, type=click.Path(),
                     help="YAML file merged over configs/default.yaml (repeatable).")(f)
    return f


def json_option(f):
    return click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")(f)


def build_config(config_files: tuple[str, ...], sets: tuple[str, ...]) -> Config:
    return load_config(config_files, sets)


def emit_json(data: Any) -> None:
    click.echo(json.dumps(data, indent=2, sort_keys=True, default=str))
