"""`embody export`: a run's validated trajectories as a robot trajectory library."""

from __future__ import annotations

import click

from embody.verdicts import plural

from embody.cli.common import emit_json, json_option


@click.command("export")
@click.argument("run")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--robot", required=True, help="Robot the trajectories must be for (robot.name).")
@click.option("--store", "store_root", default="embody-store", show_default=True,
              type=click.Path(file_okay=False), help="Artifact store root.")
@click.option("--format", "fmt", type=click.Choice(["npz", "csv"]), default="npz",
              show_default=True, help="npz (q, joint names, dt, source, validation) or csv.")
@click.option("--include-rejected/--exclude-rejected", default=False, show_default=True,
              help="Keep sequences the critic rejected (default: exclude them, like failed "
                   "ones; runs without a critic have none).")
@json_option
def command(run: str, out: str, robot: str, store_root: str, fmt: str, include_rejected: bool,
            as_json: bool) -> int:
    """Write one file per valid sequence of RUN into OUT, plus library.csv and excluded.csv.

    Sequences with joint-limit or velocity-limit violations or self-collision frames, and
    sequences the run failed, are excluded and listed. So are sequences the critic rejected,
    unless --include-rejected is given. Exit 1 when any was excluded.
    """
    from embody.report.reader import run_trajectories
    from embody.report.library import export_library

    trajectories, failed = run_trajectories(store_root, run, robot)
    if not include_rejected:
        rejected = [t for t in trajectories if t.validation.get("accepted") is False]
        trajectories = [t for t in trajectories if t.validation.get("accepted") is not False]
        failed = [*failed, *((t.id, "critic rejected (--include-rejected keeps it)")
                             for t in rejected)]
    library, excluded = export_library(trajectories, out, fmt, failed)  # type: ignore[arg-type]
    if as_json:
        emit_json({"out": out, "exported": library["id"].tolist(),
                   "excluded": excluded[["id", "reason"]].to_dict("records")})
    else:
        click.echo(f"exported {plural(len(library), 'trajectory', 'trajectories')} to {out} "
                   "(library.csv)")
        for row in excluded.itertuples():
            click.echo(f"excluded {row.id}: {row.reason}")
    return 1 if len(excluded) else 0
