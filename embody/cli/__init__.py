"""The `embody` command line.

One module per command in this package (`embody/cli/<name>.py` exposing `command`), loaded
lazily so `embody inspect` never pays for Prefect or MuJoCo imports.
Exit codes: 0 success, 1 some sequences failed (the rest done), 2 bad input, usage or config.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

import click

from embody.errors import ConfigError, EmbodyError, InputError, UsageError

#: command name → module under embody.cli (a module may be absent while a stage is unbuilt).
COMMANDS = {
    "run": "run", "serve": "serve", "store": "store_cmd", "report": "report", "export": "export",
    "play": "play", "synth": "synth", "inspect": "inspect_cmd", "collide": "collide",
    "retarget": "retarget", "refine": "refine", "config": "config_cmd",
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(n for n, m in COMMANDS.items()
                      if importlib.util.find_spec(f"embody.cli.{m}") is not None)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        module = COMMANDS.get(name)
        if module is None or importlib.util.find_spec(f"embody.cli.{module}") is None:
            return None
        return importlib.import_module(f"embody.cli.{module}").command


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="embody")
def cli() -> None:
    """Turn generated SMPL-X signing into validated robot joint trajectories."""


#: Longest error line printed: a message quoting hostile input stays readable.
MAX_ERROR_CHARS = 1000


def one_line(exc: BaseException) -> str:
    """The error's message on one line of at most `MAX_ERROR_CHARS` characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= MAX_ERROR_CHARS else text[: MAX_ERROR_CHARS - 3] + "..."


def main(argv: list[str] | None = None) -> int:
    """Entry point: maps embody's errors onto the exit-code convention with one-line messages."""
    try:
        rv = cli.main(args=argv, prog_name="embody", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        return 130
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        exc.show()
        return 2
    except (InputError, ConfigError, UsageError) as exc:
        click.echo(f"error: {one_line(exc)}", err=True)
        return 2
    except EmbodyError as exc:
        click.echo(f"error: {one_line(exc)}", err=True)
        return 1
    code = rv if isinstance(rv, int) else 0
    if argv is None:
        sys.exit(code)
    return code
