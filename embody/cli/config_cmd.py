"""`embody config`: print the effective configuration."""

from __future__ import annotations

import click
import yaml

from embody.cli.common import build_config, config_options, json_option, emit_json


@click.command("config")
@config_options
@json_option
def command(config_files: tuple[str, ...], sets: tuple[str, ...], as_json: bool) -> int:
    """Print the effective configuration (defaults + files + --set)."""
    cfg = build_config(config_files, sets)
    data = cfg.model_dump(mode="json")
    if as_json:
        emit_json(data)
    else:
        click.echo(yaml.safe_dump(data, sort_keys=False), nl=False)
    return 0
