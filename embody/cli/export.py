"""`embody export`: a run's validated trajectories as a robot trajectory library; `--check`
re-validates a library (yours or one you received) from its files alone."""

from __future__ import annotations

import click

from embody.verdicts import export_valid, plural

from embody.cli.common import emit_json, json_option
from embody.export.formats import FORMATS


def _shown(text: object, limit: int = 200) -> str:
    """Text from a library or run as one short printable line: control characters (ANSI
    escapes, newlines) are shown escaped, never sent to the terminal; long text is cut."""
    text = str(text)
    cut = text[:limit] + ("…" if len(text) > limit else "")
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in cut)


@click.command("export")
@click.argument("args", nargs=-1, metavar="RUN OUT | --check DIR")
@click.option("--robot", default=None, help="Robot the trajectories must be for (robot.name); "
              "with --check, overrides the robot library.json names.")
@click.option("--store", "store_root", default="embody-store", show_default=True,
              type=click.Path(file_okay=False),
              help="Artifact store: a directory, or s3://bucket/prefix (gs://, az://).")
@click.option("--format", "fmt", type=click.Choice(list(FORMATS)), default="npz",
              show_default=True, help="npz (q, joint names, dt, source, validation), csv, "
              "gmr (GMR motion pickle) or beyondmimic (BeyondMimic csv_to_npz input).")
@click.option("--check", is_flag=True, help="Re-validate the library in DIR with MuJoCo from "
              "its files alone; exit 1 if any file fails, 2 if the library is malformed "
              "(see docs/security.md for what it guarantees).")
@click.option("--include-rejected/--exclude-rejected", default=False, show_default=True,
              help="Keep sequences the critic rejected (default: exclude them, like failed "
                   "ones; runs without a critic have none).")
@json_option
def command(args: tuple[str, ...], robot: str | None, store_root: str, fmt: str, check: bool,
            include_rejected: bool, as_json: bool) -> int:
    """Write one file per valid sequence of RUN into OUT, plus library.csv, library.json and
    excluded.csv.

    The exported array is the control-rate trajectory the run's metrics step validated; every
    file is read back as its consumer reads it and re-validated (joint limits, velocity limits,
    MuJoCo self-collision at every sample). Sequences that fail, and sequences the run failed,
    are excluded and listed. So are sequences the critic rejected, unless --include-rejected is
    given. Exit 1 when any was excluded.
    """
    if check:
        if len(args) != 1:
            raise click.UsageError("--check takes one argument: the library directory")
        return _check(args[0], robot, as_json)
    if len(args) != 2:
        raise click.UsageError("expected RUN OUT (or --check DIR)")
    if robot is None:
        raise click.UsageError("Missing option '--robot'.")
    from embody.export.library import export_library
    from embody.export.runs import run_robot, run_trajectories

    from embody.store import check_run_name

    run, out = args
    check_run_name(run, "RUN")
    trajectories, failed = run_trajectories(store_root, run, robot)
    skipped_valid = 0  # export-valid sequences the default leaves out (the run's verdict line says so too)
    if not include_rejected:
        rejected = [t for t in trajectories if t.validation.get("accepted") is False]
        trajectories = [t for t in trajectories if t.validation.get("accepted") is not False]
        failed = [*failed, *((t.id, "critic rejected (--include-rejected keeps it)")
                             for t in rejected)]
        skipped_valid = sum(export_valid(t.validation) for t in rejected)
    library, excluded = export_library(trajectories, out, fmt, failed,  # type: ignore[arg-type]
                                       robot=run_robot(store_root, run))
    if as_json:
        emit_json({"out": out, "format": fmt, "exported": library["id"].tolist(),
                   "excluded": excluded[["id", "reason"]].to_dict("records"),
                   "rejected_export_valid": skipped_valid})
    else:
        click.echo(f"exported {plural(len(library), 'trajectory', 'trajectories')} ({fmt}) to "
                   f"{out} (library.csv, library.json)")
        for row in excluded.itertuples():
            click.echo(f"excluded {_shown(row.id)}: {_shown(row.reason)}")
        if skipped_valid:
            click.echo(f"{plural(skipped_valid, 'export-valid sequence')} left out because the "
                       "critic rejected "
                       f"{'it' if skipped_valid == 1 else 'them'}: --include-rejected includes "
                       f"{'it' if skipped_valid == 1 else 'them'}", err=True)
    return 1 if len(excluded) else 0


def _check(lib_dir: str, robot_name: str | None, as_json: bool) -> int:
    from embody.export.library import VIOLATION_KEYS, check_library
    PHYSICS_FIGURES = ("torque_over_samples", "saturated_steps", "palm_err_p95_mm",
                       "sim_contact_samples", "zmp_margin_min_mm")

    robot = None
    if robot_name:
        from pydantic import ValidationError

        from embody.config.robot import RobotConfig
        from embody.errors import UsageError
        from embody.robot import load_robot
        try:
            cfg = RobotConfig(name=robot_name)
        except ValidationError:
            raise UsageError("--robot: not a robot name ([A-Za-z0-9_.-]+)") from None
        robot = load_robot(cfg)
    table = check_library(lib_dir, robot)
    bad = table[~table["ok"].astype(bool)]
    if as_json:
        emit_json({"library": lib_dir, "checked": len(table), "failed": bad["id"].tolist(),
                   "rows": table.to_dict("records")})
    else:
        for row in table.to_dict("records"):
            counts = " ".join(f"{k}={row[k]:g}" for k in VIOLATION_KEYS if k in row and row[k] == row[k])
            counts += "".join(f" {k}={row[k]:g}" for k in PHYSICS_FIGURES
                              if isinstance(row.get(k), (int, float)) and row[k] == row[k])
            click.echo(f"{'ok  ' if row['ok'] else 'FAIL'} {_shown(row['id'])}: {counts} "
                       f"{_shown(row['error'])}".rstrip())
        click.echo(f"checked {len(table)} files in {_shown(lib_dir)}: {len(bad)} failed")
    return 1 if len(bad) else 0
