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


def input_options(f):
    """`--fps`, `--up-axis`, `--hands`: override what the input files (or their dataset's
    documented defaults) say; they set `io.fps`, `io.up_axis`, `io.hands`."""
    f = click.option("--hands", type=click.Choice(["absolute", "relative"]), default=None,
                     help="Source hand convention [default: from the file or its dataset].")(f)
    f = click.option("--up-axis", "up_axis", type=click.Choice(["y", "z", "camera"]), default=None,
                     help="Source up axis; camera = OpenCV frame, y down [default: detected].")(f)
    f = click.option("--fps", type=click.FloatRange(min=0, min_open=True), default=None,
                     help="Source frame rate [default: from the file or its dataset's rate].")(f)
    return f


def input_sets(fps: float | None, up_axis: str | None, hands: str | None) -> tuple[str, ...]:
    """The `--set`s equivalent to the input options (so config validation is shared)."""
    pairs = (("io.fps", fps), ("io.up_axis", up_axis), ("io.hands", hands))
    return tuple(f"{key}={json.dumps(value)}" for key, value in pairs if value is not None)


def load_input(path: str, cfg: Config) -> Any:
    """`embody.io.load` with the config's `io` overrides and bounds."""
    from embody.io import load

    return load(path, fps=cfg.io.fps, up_axis=cfg.io.up_axis, hands=cfg.io.hands, limits=cfg.io)


def json_option(f):
    return click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")(f)


def build_config(config_files: tuple[str, ...], sets: tuple[str, ...]) -> Config:
    return load_config(config_files, sets)


def emit_json(data: Any) -> None:
    click.echo(json.dumps(data, indent=2, sort_keys=True, default=str))
