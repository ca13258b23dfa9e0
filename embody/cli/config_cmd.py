"""`embody config`: print the effective configuration."""

from __future__ import annotations

import click
import yaml

from embody.cli.common import build_config, config_options, emit_json, json_option
from embody.config import Config


@click.command("config")
@config_options
@click.option("--model-defaults", is_flag=True,
              help="Print the typed models' defaults only (regenerates configs/default.yaml).")
@json_option
def command(config_files: tuple[str, ...], sets: tuple[str, ...], model_defaults: bool,
            as_json: bool) -> int:
    """Print the effective configuration (defaults + files + --set)."""
    cfg = Config() if model_defaults else build_config(config_files, sets)
    data = cfg.model_dump(mode="json")
    if as_json:
        emit_json(data)
    else:
        click.echo(yaml.safe_dump(data, sort_keys=False), nl=False)
    return 0
