"""`embody serve --cron`: serve the dataset flow on a schedule through a Prefect server."""

from __future__ import annotations

import os
from typing import Any

import click

from embody.cli.run import check_up_front, config_from_options, prepare, run_options

EXPLANATION = """\
Schedules need a persistent Prefect server: the ephemeral server that `embody run` starts lives
only as long as one run, so a scheduled deployment on it never fires.

  1. start one:   prefect server start            (keep it running; Postgres for big datasets)
  2. point at it: export PREFECT_API_URL=http://127.0.0.1:4200/api
  3. serve:       embody serve --cron "0 3 * * *" [run options]

Alternative without a server: an OS cron entry that calls `embody run` (reruns are cheap,
every finished step is a store hit), e.g.
  0 3 * * *  cd /data && embody run /data/signs --store /data/embody-store
See docs/orchestration.md."""


def api_health(url: str | None, timeout: float = 5.0) -> str | None:
    """Why the Prefect API at `url` is unusable for schedules, or None when it is healthy."""
    if not url:
        return "PREFECT_API_URL is not set"
    import httpx

    try:
        response = httpx.get(url.rstrip("/") + "/health", timeout=timeout)
    except httpx.HTTPError as exc:
        return f"no Prefect server reachable at {url} ({type(exc).__name__})"
    if response.status_code != 200:
        return f"{url}/health answered HTTP {response.status_code}"
    return None


@click.command("serve")
@click.option("--cron", required=True, help='Cron schedule, e.g. "0 3 * * *".')
@click.option("--deployment", default="embody-nightly", show_default=True,
              help="Deployment name shown in the Prefect UI.")
@run_options
def command(dataset: str | None, split: str | None, config_files: tuple[str, ...],
            sets: tuple[str, ...], cron: str, deployment: str, **options: Any) -> int:
    """Serve `embody run DATASET ...` as a Prefect deployment on a cron schedule."""
    cfg = config_from_options(config_files, sets, **options)
    from embody.flows.env import configure

    check_up_front(cfg, dataset)  # nothing created for a bad store path or VLM config
    from embody.cli.run import local_home
    configure(local_home(cfg.run.store))  # before Prefect is imported
    from prefect.client.schemas.schedules import CronSchedule

    try:
        CronSchedule(cron=cron)
    except ValueError as exc:
        msg = str(exc).splitlines()[-2].strip() if "\n" in str(exc) else str(exc)
        raise click.BadParameter(msg, param_hint="--cron") from None
    problem = api_health(os.environ.get("PREFECT_API_URL"))
    if problem:
        click.echo(f"error: {problem}.\n\n{EXPLANATION}", err=True)
        return 2
    path = prepare(dataset, split, cfg)
    from embody.flows.dataset import dataset_flow
    from embody.flows.runners import make_task_runner

    click.echo(f"serving deployment {deployment!r} ({cron}) against "
               f"{os.environ['PREFECT_API_URL']}; Ctrl-C stops", err=True)
    dataset_flow.with_options(task_runner=make_task_runner(cfg.run)).serve(
        name=deployment, cron=cron,
        parameters={"dataset": str(path), "split": split, "config": cfg.model_dump(mode="json")})
    return 0
