"""`embody config`: print the effective configuration, or explain its keys."""

from __future__ import annotations

import click
import yaml

from embody.cli.common import build_config, config_options, emit_json, json_option
from embody.config import Config


@click.command("config")
@config_options
@click.option("--model-defaults", is_flag=True,
              help="Print the typed models' defaults only (regenerates configs/default.yaml).")
@click.option("--explain", is_flag=True,
              help="List the keys a user sets (value, meaning, unit) apart from internal tuning.")
@json_option
def command(config_files: tuple[str, ...], sets: tuple[str, ...], model_defaults: bool,
            explain: bool, as_json: bool) -> int:
    """Print the effective configuration (defaults + files + --set)."""
    cfg = Config() if model_defaults else build_config(config_files, sets)
    if explain:
        from embody.config.explain import USER_KEYS, config_keys, describe, explain as explained
        if as_json:
            emit_json({"user": {k: describe(k, cfg) for k in config_keys(cfg) if k in USER_KEYS},
                       "tuning": {k: describe(k, cfg) for k in config_keys(cfg) if k not in USER_KEYS}})
        else:
            click.echo(explained(cfg), nl=False)
        return 0
    data = cfg.model_dump(mode="json")
    if as_json:
        emit_json(data)
    else:
        click.echo(yaml.safe_dump(data, sort_keys=False), nl=False)
    return 0
