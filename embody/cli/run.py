"""`embody run`: the whole pipeline over a dataset, cached in the artifact store."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from embody.cli.common import build_config, config_options, emit_json, json_option
from embody.config import Config
from embody.verdicts import plural, verdict_line


def run_options(f):
    """Options shared by `run` and `serve` (they configure the same flow)."""
    for opt in reversed([
        click.argument("dataset", required=False, type=click.Path()),
        click.option("--split", default=None, help="SOKE split (train/val/test)."),
        click.option("--store", default=None, type=click.Path(file_okay=False),
                     help="Artifact store directory [default: run.store, ./embody-store]."),
        click.option("--limit", type=int, default=None, help="Only the first N sequences."),
        click.option("--workers", type=int, default=None, help="Concurrent tasks."),
        click.option("--runner", type=click.Choice(["threads", "processes", "dask"]), default=None),
        click.option("--dask-address", default=None, help="tcp://host:port of a Dask scheduler."),
        click.option("--batch-size", type=int, default=None, help="Sequences per task run."),
        click.option("--critic", type=click.Choice(["geometric", "vlm", "none"]), default=None,
                     help="Critic of the refinement loop [default: critic.kind; none skips it]."),
        click.option("--render/--no-render", default=None,
                     help="Store each sequence's comparison sheet and preview [default: on]."),
        click.option("--robot", default=None, help="Robot definition name (robot.name)."),
        click.option("--name", default=None, help="Run name [default: from the dataset]."),
        config_options,
    ]):
        f = opt(f)
    return f


def config_from_options(config_files: tuple[str, ...], sets: tuple[str, ...],
                        **options: Any) -> Config:
    """Config files and `--set`s, then the dedicated options on top (validated the same way)."""
    keys = {"store": "run.store", "limit": "run.limit", "workers": "run.workers",
            "runner": "run.runner", "dask_address": "run.dask_address",
            "batch_size": "run.batch_size", "robot": "robot.name", "name": "run.name",
            "render": "run.render"}
    extra = [f"{keys[k]}={json.dumps(v)}" for k, v in options.items()
             if k in keys and v is not None]
    critic = options.get("critic")
    if critic == "none":
        extra.append("run.critic=false")
    elif critic is not None:
        extra += ["run.critic=true", f"critic.kind={critic}"]
    return build_config(config_files, tuple(sets) + tuple(extra))


def prepare(dataset: str | None, split: str | None, cfg: Config) -> Path:
    """Resolve and list the dataset before Prefect starts, so bad input fails fast (exit 2)."""
    from embody.io import load_dataset
    from flows.env import configure

    configure(cfg.run.store)
    from flows.dataset import resolve_dataset
    path = resolve_dataset(dataset, cfg)
    load_dataset(path, split)
    return path


def _failure_table(summary: dict[str, Any]) -> str:
    rows = [(f["id"], f["step"] or "", (f["error"] or "").splitlines()[0][:100])
            for f in summary["failures"]]
    w_id = max([len("sequence")] + [len(r[0]) for r in rows])
    w_step = max([len("step")] + [len(r[1]) for r in rows])
    lines = [f"{'sequence':<{w_id}}  {'step':<{w_step}}  error"]
    lines += [f"{a:<{w_id}}  {b:<{w_step}}  {c}" for a, b, c in rows]
    return "\n".join(lines)


@click.command("run")
@run_options
@click.option("--progress/--no-progress", default=True, help="Per-stage progress on stderr.")
@json_option
def command(dataset: str | None, split: str | None, config_files: tuple[str, ...],
            sets: tuple[str, ...], progress: bool, as_json: bool, **options: Any) -> int:
    """Run the pipeline over DATASET (default: the synthetic set in <store>/data).

    DATASET is a folder of motion files, a SOKE root (with --split) or a CSV manifest. Reruns
    are cheap: every step is cached by content key, so only what changed is recomputed.
    """
    cfg = config_from_options(config_files, sets, **options)
    say = (lambda text: click.echo(f"embody run: {text}", err=True)) if progress else (
        lambda text: None)
    say(f"starting: dataset {dataset or 'synthetic (default)'}, robot {cfg.robot.name}, "
        f"store {cfg.run.store}")
    path = prepare(dataset, split, cfg)
    say("checking the store for results of every step")
    from flows.warm import run_cached

    summary = run_cached(path, cfg, split=split, progress=progress)
    if summary is None:
        say("starting Prefect (a local server: ~10 s) and the pipeline")
        from flows.dataset import run_flow

        summary = run_flow(path, cfg, split=split, progress=progress)
    if as_json:
        emit_json(summary)
    else:
        computed = ", ".join(f"{k} {v}" for k, v in summary["computed"].items())
        click.echo(f"run {summary['run']}: {summary['ok']}/{summary['total']} sequences ok"
                   f" in {summary['elapsed_s']:.1f} s (computed: {computed or 'nothing'})")
        click.echo(f"manifest: {summary['manifest']}")
        click.echo(f"table:    {summary['table']}")
        if summary.get("report"):
            click.echo(f"report:   {summary['report']}")
        if summary.get("report_error"):
            click.echo(f"warning: report not built: {summary['report_error']}", err=True)
    if summary.get("verdicts"):  # the closing summary: three verdicts side by side
        click.echo(f"verdicts: {verdict_line(summary['verdicts'])}", err=True)
    if summary["failed"]:
        click.echo(f"{plural(summary['failed'], 'sequence')} failed:\n{_failure_table(summary)}", err=True)
        return 1
    return 0
