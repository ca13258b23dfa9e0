"""`embody export`: a run's validated trajectories as a robot trajectory library."""

from __future__ import annotations

import click

from embody.cli.common import emit_json, json_option


@click.command("export")
@click.argument("run")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--robot", required=True, help="Robot the trajectories must be for (robot.name).")
@click.option("--store", "store_root", default="embody-store", show_default=True,
              type=click.Path(file_okay=False), help="Artifact store root.")
@click.option("--format", "fmt", type=click.Choice(["npz", "csv"]), default="npz",
              show_default=True, help="npz (q, joint names, dt, source, validation) or csv.")
@json_option
def command(run: str, out: str, robot: str, store_root: str, fmt: str, as_json: bool) -> int:
    """Write one file per valid sequence of RUN into OUT, plus library.csv and excluded.csv.

    Sequences with joint-limit or velocity-limit violations or self-collision frames, and
    sequences the run failed, are excluded and listed. Exit 1 when any was excluded.
    """
    from embody.report.reader import run_trajectories
    from embody.report.library import export_library
    from store import check_run_name

    check_run_name(run, "RUN")
    trajectories, failed = run_trajectories(store_root, run, robot)
    library, excluded = export_library(trajectories, out, fmt, failed)  # type: ignore[arg-type]
    if as_json:
        emit_json({"out": out, "exported": library["id"].tolist(),
                   "excluded": excluded[["id", "reason"]].to_dict("records")})
    else:
        click.echo(f"exported {len(library)} trajectories to {out} (library.csv)")
        for row in excluded.itertuples():
            click.echo(f"excluded {row.id}: {row.reason}")
    return 1 if len(excluded) else 0
