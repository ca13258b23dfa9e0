"""`embody run`: the whole pipeline over a dataset, cached in the artifact store."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from embody.cli.common import build_config, config_options, emit_json, input_options, json_option
from embody.config import Config
from embody.verdicts import plural, verdict_line


def run_options(f):
    """Options shared by `run` and `serve` (they configure the same flow)."""
    for opt in reversed([
        click.argument("dataset", required=False, type=click.Path()),
        click.option("--split", default=None, help="SOKE split (train/val/test)."),
        click.option("--store", default=None,
                     help="Artifact store: a directory, or s3://bucket/prefix (gs://, az://, "
                          "file://) [default: run.store, ./embody-store]."),
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
        click.option("--name", default=None,
                     help="Run name [default: <dataset>[-<split>].<robot>, e.g. "
                          "synth-n24-s0.unitree_g1_dex3]."),
        click.option("--overwrite", is_flag=True, default=False,
                     help="Reuse a run name that holds a run of another robot or dataset."),
        input_options,
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
            "render": "run.render", "fps": "io.fps", "up_axis": "io.up_axis",
            "hands": "io.hands"}
    extra = [f"{keys[k]}={json.dumps(v)}" for k, v in options.items()
             if k in keys and v is not None]
    critic = options.get("critic")
    if critic == "none":
        extra.append("run.critic=false")
    elif critic is not None:
        extra += ["run.critic=true", f"critic.kind={critic}"]
    return build_config(config_files, tuple(sets) + tuple(extra))


def check_store_path(text: str) -> Path | str:
    """A local store's parent must exist; an object store's URL must be one the store serves
    (`store.artifacts.store_location`): checked before anything is created (another URL would
    otherwise become a junk `./http:/...` folder)."""
    from embody.errors import ConfigError
    from embody.store.artifacts import store_location

    if text.startswith(("http:", "https:")) or (text.startswith("file:")
                                                and not text.startswith("file://")):
        raise ConfigError("run.store", f"the store must be a local path or an object-store URL "
                          f"(s3://, gs://, az://, file://), got {text!r}")
    where = store_location(text)
    if isinstance(where, str):
        return where
    path = where.expanduser().absolute()
    if path.exists() and not path.is_dir():
        raise ConfigError("run.store", f"{path} exists and is not a directory")
    if not path.exists() and not path.parent.is_dir():
        raise ConfigError("run.store", f"the parent folder of {path} does not exist")
    return path


def check_up_front(cfg: Config, dataset: str | None) -> None:
    """Config that is knowable before the run (exit 2, nothing created): store path, run name,
    and for the VLM critic its base_url and API key."""
    from embody.store import check_run_name

    check_store_path(cfg.run.store)
    if cfg.run.name:
        check_run_name(cfg.run.name)
    if cfg.run.critic and cfg.critic.kind == "vlm":
        from embody.critic.vlm import check_config
        check_config(cfg.critic.vlm)


def prepare(dataset: str | None, split: str | None, cfg: Config, overwrite: bool = False) -> Path:
    """Validate config and resolve and list the dataset before Prefect starts, so bad input
    fails fast (exit 2) with nothing created in the store (Prefect's home included: the caller
    configures it once the dataset is accepted); a reused run name of another robot or dataset
    is refused."""
    from embody.io import load_dataset
    from embody.io.remote import is_url

    check_up_front(cfg, dataset)
    from embody.flows.dataset import check_run_reuse, resolve_dataset, run_name
    from embody.store import ArtifactStore

    store = ArtifactStore(cfg.run.store)
    if dataset is None and not store.is_local:  # the synthetic set is generated locally
        from embody.synth import default_dataset
        dataset = str(default_dataset(store.work_dir / "data", n=cfg.run.synth_n,
                                      seed=cfg.run.seed))
    path = resolve_dataset(dataset, cfg)
    load_dataset(dataset if dataset and is_url(dataset) else path, split, cfg.io)  # errors name URLs
    check_run_reuse(cfg.run.store, run_name(cfg, path, split), path, split, cfg.robot.name,
                    overwrite)
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
            sets: tuple[str, ...], progress: bool, as_json: bool, overwrite: bool,
            **options: Any) -> int:
    """Run the pipeline over DATASET (default: the synthetic set in <store>/data).

    DATASET is a folder of motion files, a SOKE root (with --split) or a CSV manifest. Reruns
    are cheap: every step is cached by content key, so only what changed is recomputed.
    """
    from embody.flows.env import configure, on_sigterm

    cfg = config_from_options(config_files, sets, **options)
    say = (lambda text: click.echo(f"embody run: {text}", err=True)) if progress else (
        lambda text: None)
    say(f"starting: dataset {dataset or 'synthetic (default)'}, robot {cfg.robot.name}, "
        f"store {cfg.run.store}")
    path = prepare(dataset, split, cfg, overwrite)
    with claim_run(path, split, cfg):
        configure(local_home(cfg.run.store))
        on_sigterm()  # SIGTERM cleans up like Ctrl-C: the ephemeral Prefect server is stopped
        return _run(path, split, cfg, say, progress, as_json)


def local_home(store_text: str) -> Path | str:
    """Where Prefect's home goes (`flows.env.configure`): inside a local store, and for an
    object store in the store's local work folder (`ArtifactStore.work_dir`)."""
    from embody.store import ArtifactStore

    store = ArtifactStore(store_text)
    return store_text if store.is_local else store.work_dir


def claim_run(path: Path, split: str | None, cfg: Config) -> Any:
    """The run name claimed for this dataset, split and robot while the run lasts (`store.claims`):
    a concurrent run of the name over other data is refused (exit 2) before anything is written."""
    from embody.flows.dataset import run_name
    from embody.store import ArtifactStore
    from embody.store.claims import claim_run

    return claim_run(ArtifactStore(cfg.run.store), run_name(cfg, path, split),
                     {"dataset": str(Path(path).expanduser().resolve()), "split": split,
                      "robot": cfg.robot.name})


def _run(path: Path, split: str | None, cfg: Config, say: Any, progress: bool,
         as_json: bool) -> int:
    """The run itself, once its input is accepted and its name claimed."""
    import errno

    say("checking the store for results of every step")
    from embody.flows.warm import run_cached

    try:
        summary = run_cached(path, cfg, split=split, progress=progress)
        if summary is None:
            say("starting Prefect (a local server: ~3 s) and the pipeline")
            from embody.flows.dataset import run_flow

            summary = run_flow(path, cfg, split=split, progress=progress)
    except OSError as exc:  # e.g. the disk filled before any sequence could record it
        reason = "no space left on device" if exc.errno == errno.ENOSPC else str(exc)
        click.echo(f"error: the run could not write to the store ({reason})", err=True)
        return 1
    if as_json:
        emit_json(summary)
    else:
        computed = ", ".join(f"{k} {v}" for k, v in summary["computed"].items())
        click.echo(f"run {summary['run']}: {summary['ok']}/{summary['total']} sequences ok"
                   f" in {summary['elapsed_s']:.1f} s (computed: {computed or 'nothing'})")
        click.echo(f"manifest: {summary['manifest']}")
        if summary.get("table"):
            click.echo(f"table:    {summary['table']}")
        if summary.get("report"):
            click.echo(f"report:   {summary['report']}")
        if summary.get("report_error"):
            click.echo(f"warning: report not built: {summary['report_error']}", err=True)
    for item in summary.get("recovered", []):
        click.echo(f"warning: {item['id']}: recomputed corrupt artifact {item['artifact']}",
                   err=True)
    for item in summary.get("layout_warnings", []):  # once per distinct warning, not per file
        ids = ", ".join(item["ids"][:3]) + (", ..." if item["count"] > 3 else "")
        click.echo(f"warning: {plural(item['count'], 'sequence')} ({ids}): {item['warning']}",
                   err=True)
    if summary.get("verdicts"):  # the closing summary: three verdicts side by side
        click.echo(f"verdicts: {verdict_line(summary['verdicts'])}", err=True)
    if summary["failed"]:
        click.echo(f"{plural(summary['failed'], 'sequence')} failed:\n{_failure_table(summary)}", err=True)
    for error in summary.get("errors", []):
        click.echo(f"error: {error}", err=True)
    if summary["failed"] or summary.get("errors"):
        return 1
    return 0
