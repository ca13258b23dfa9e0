"""Every `embody` command the docs show is read out of the docs and checked against the CLI.

Where the commands come from: fenced ```bash blocks and indented code blocks of README.md and
docs/*.md, inline code spans that start with `embody `, and the README's command table.

What is checked, honestly:
- Every documented command line is parsed by the real click command (options, choices, types,
  arguments): a renamed option, a removed choice or a wrong argument count fails here.
- Cheap commands run for real with tiny inputs: `embody config --model-defaults` (and its
  output must equal configs/default.yaml, as the docs claim), `embody store ls|verify|gc
  --dry-run` on an empty store, `embody synth OUT --n 2`, `embody inspect` on its output.
- Every command of the table answers `--help` (exit 0), and each option and choice the table
  lists exists on that command.
- Expensive commands (`embody run`, `report --ablation`, `serve`, `export`, `refine`, ...) are
  only parsed, not executed: they take minutes or need a server; the end-to-end tests
  (test_report_run.py, test_cli_run.py) run them on tiny data.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import click
import pytest

from embody.cli import cli, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "reports" / "README.md"]


def _clean(line: str) -> str:
    """One shell line → the embody invocation in it (comments, redirections, prefixes gone)."""
    line = re.sub(r"\s#\s.*$", "", line)
    line = re.split(r"\s\d?>>?\s", line)[0]
    line = re.sub(r"^.*?(?:\S*/)?embody\s", "embody ", line, count=1)
    return line.strip()


def _expand(command: str) -> list[str]:
    """`embody store ls | verify | gc [--dry-run]` → one command per alternative, `[x]` → x."""
    command = command.replace("[", "").replace("]", "")
    parts = [p.strip() for p in command.split(" | ")]
    if len(parts) == 1:
        return [command]
    head, last = parts[0].rsplit(" ", 1)
    return [f"{head} {last}"] + [f"{head} {alt}" for alt in parts[1:]]


def documented_commands() -> list[tuple[str, str]]:
    """(where, command) for every concrete `embody` command line in the docs."""
    out = []
    for doc in DOCS:
        text = doc.read_text()
        blocks = re.findall(r"```(?:bash|sh|console)?\n(.*?)```", text, re.S)
        blocks += ["\n".join(line[4:] for line in m.group(0).splitlines())
                   for m in re.finditer(r"(?m)(?:^    \S.*\n)+", text)]
        lines = [seg for b in blocks for line in b.splitlines() for seg in line.split(" && ")]
        prose = re.sub(r"(?m)^\|.*$", "", text)  # the command table is checked on its own
        spans = [s for s in re.findall(r"`(embody [^`]+)`", prose) if "[" not in s]
        for raw in lines + spans:
            if not re.search(r"(^|[\s/])embody\s", raw) or "<" in raw:
                continue
            cleaned = _clean(raw)
            for cmd in _expand(cleaned):
                out.append((f"{doc.relative_to(ROOT)}: {raw.strip()}", cmd))
    return out


def table_rows() -> list[str]:
    """The synopses in the README's command table (`| \\`embody ...\\` | what |`)."""
    text = (ROOT / "README.md").read_text()
    return [m.replace("\\|", "|") for m in re.findall(r"(?m)^\| `(embody (?:[^`]|\\`)+)` \|", text)]


def _resolve(tokens: list[str]) -> tuple[click.Command, list[str], str]:
    """The click command a token list names (descending into groups) and its own args."""
    cmd: click.Command = cli
    args = tokens[1:]
    name = "embody"
    while isinstance(cmd, click.Group) and args and not args[0].startswith("-"):
        ctx = click.Context(cmd, info_name=name)
        sub = cmd.get_command(ctx, args[0])
        assert sub is not None, f"no command {args[0]!r} under {name!r}"
        cmd, name, args = sub, f"{name} {args[0]}", args[1:]
    return cmd, args, name


CONCRETE = documented_commands()


def test_the_docs_show_commands() -> None:
    assert len(CONCRETE) >= 8, CONCRETE  # the reader found them (guards the parser itself)
    assert any(c == "embody run" for _, c in CONCRETE)
    assert len(table_rows()) >= 10


def parse_error(command: str) -> str | None:
    """Why the CLI would reject `command` at parse time (None: it parses)."""
    cmd, args, name = _resolve(shlex.split(command))
    try:
        cmd.make_context(name, list(args))  # parses exactly as a real call would
    except click.exceptions.Exit:
        pass
    except click.ClickException as exc:
        return exc.format_message()
    return None


@pytest.mark.parametrize("where,command", CONCRETE, ids=[c for _, c in CONCRETE])
def test_documented_command_parses(where: str, command: str) -> None:
    error = parse_error(command)
    assert error is None, f"{where}: {error}"


def test_the_parse_check_catches_wrong_commands() -> None:
    assert parse_error("embody run --critic nope")
    assert parse_error("embody run --no-such-option")
    assert parse_error("embody export run out --robot r --format xyz")
    assert parse_error("embody run data --limit many")
    assert _clean("cd /data && /opt/x/bin/embody run /d --json >> log 2>> err") == "embody run /d --json"


@pytest.mark.parametrize("synopsis", table_rows())
def test_table_synopsis_matches_the_cli(synopsis: str) -> None:
    words = [w for w in re.split(r"[\s\[\]]+", synopsis) if w]
    head = ["embody"] + [w for w in words[1:3] if re.fullmatch(r"[a-z]+", w)]
    if len(head) == 3 and "|" in synopsis.split()[2]:
        head = head[:2]  # `embody store ls|verify|gc`: alternatives, not a sub-sub-command
    cmd, _, name = _resolve(head[:2] if head[1] != "store" else head[:2])
    assert main([*name.split()[1:], "--help"]) == 0
    params = {o: p for p in cmd.params for o in (*p.opts, *p.secondary_opts)}
    if isinstance(cmd, click.Group):
        subs = re.split(r"\|", synopsis.split()[2])
        assert set(subs) <= set(cmd.list_commands(click.Context(cmd))), synopsis
        return
    for m in re.finditer(r"(--[a-z][a-z-]*)(?:[ =]([a-z0-9]+(?:\|[a-z0-9]+)+))?", synopsis):
        option, choices = m.group(1), m.group(2)
        assert option in params, f"{synopsis}: {name} has no {option}"
        if choices:
            kind = params[option].type
            assert isinstance(kind, click.Choice), (synopsis, option)
            assert set(choices.split("|")) == set(kind.choices), (synopsis, option)


def test_cheap_commands_run_for_real(tmp_path, capsys) -> None:
    """The cheap documented commands, executed with tiny inputs."""
    assert main(["config", "--model-defaults"]) == 0
    out = capsys.readouterr().out
    assert out == (ROOT / "configs" / "default.yaml").read_text()  # as docs/ARCHITECTURE.md says
    store = tmp_path / "store"
    store.mkdir()
    for sub in (["ls"], ["verify"], ["gc", "--dry-run"]):
        assert main(["store", *sub, "--store", str(store)]) == 0, sub
    assert main(["synth", str(tmp_path / "syn"), "--n", "2", "--seed", "0"]) == 0
    assert "wrote 2 sequences" in capsys.readouterr().out
    first = sorted(p for p in (tmp_path / "syn").rglob("*.npz"))[0]
    assert main(["inspect", str(first)]) == 0
    assert "fps" in capsys.readouterr().out
    assert main(["report", "--help"]) == 0 and "latest main run" in capsys.readouterr().out
