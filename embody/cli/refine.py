"""`embody refine IN OUT`: IK plus critic refinement of one motion file, with renders."""

from __future__ import annotations

import json
from pathlib import Path

import click

from embody.verdicts import plural
import numpy as np

from embody.cli.common import (build_config, config_options, emit_json, input_options, input_sets,
                               json_option, load_input)


@click.command("refine")
@click.argument("in_path", metavar="IN", type=click.Path())
@click.argument("out", metavar="OUT", type=click.Path(file_okay=False))
@click.option("--critic", type=click.Choice(["geometric", "vlm"]), default=None,
              help="Critic to use [default: critic.kind].")
@input_options
@config_options
@json_option
def command(in_path: str, out: str, critic: str | None, fps: float | None, up_axis: str | None,
            hands: str | None, config_files: tuple[str, ...], sets: tuple[str, ...],
            as_json: bool) -> int:
    """Load IN, shape-fit, build targets, solve IK, refine with the critic; write OUT/.

    OUT gets sheet.png (final comparison sheet), the preview, refine.npz (every round's q and
    working targets, plus the JSON record under `attrs`) and, for the VLM critic, each round's
    sheet and keyframes as the critic saw them.
    """
    cfg = build_config(config_files, sets + ((f"critic.kind={critic}",) if critic else ())
                       + input_sets(fps, up_axis, hands))
    from embody.body import load_body_model
    from embody.critic import make_critic, refine, refine_table
    from embody.retarget import build_targets, shape_fit, solve
    from embody.retarget.ik import without_dynamics_limits
    from embody.robot import load_robot

    motion = load_input(in_path, cfg)
    critic_impl = make_critic(cfg.critic)  # fails fast (e.g. a missing VLM key) before the IK
    robot = load_robot(cfg.robot)
    body = load_body_model(cfg.body)
    fit = shape_fit(robot, body, cfg.ik)
    targets = build_targets(motion, body, fit, robot, cfg.ik)
    solution = solve(robot, targets, without_dynamics_limits(cfg.ik))  # refine limits the export
    out_dir = Path(out)
    result = refine(motion, body, fit, robot, targets, solution, cfg.critic, cfg.ik, cfg.render,
                    out_dir=out_dir, critic=critic_impl)
    attrs = result.to_attrs()
    np.savez(out_dir / "refine.npz", **result.to_arrays(), attrs=np.array(json.dumps(attrs)))
    table = refine_table([result])
    files = sorted(p.name for p in out_dir.iterdir())
    if as_json:
        emit_json({"input": in_path, "out": out, "critic": cfg.critic.kind,
                   "accepted": result.accepted, "rounds": len(result.rounds),
                   "table": json.loads(table.to_json(orient="index")), "files": files})
    else:
        click.echo(table.to_string(float_format=lambda v: f"{v:.2f}"))
        click.echo(f"{plural(len(result.rounds), 'round')}, accepted: {result.accepted}; "
                   f"wrote {plural(len(files), 'file')} to {out}")
    return 0
