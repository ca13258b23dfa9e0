"""`embody retarget IN OUT.npz`: one motion file → robot joint trajectory (npz)."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from embody.cli.common import build_config, config_options, emit_json, json_option


@click.command("retarget")
@click.argument("in_path", metavar="IN", type=click.Path())
@click.argument("out_path", metavar="OUT.npz", type=click.Path())
@click.option("--robot", "robot_name", default=None, help="Robot definition name (overrides robot.name).")
@config_options
@json_option
def command(in_path: str, out_path: str, robot_name: str | None, config_files: tuple[str, ...],
            sets: tuple[str, ...], as_json: bool) -> int:
    """Retarget one motion file to the robot and write q, joint names, fps, q at control rate and metrics."""
    from embody.body import load_body_model
    from embody.io import load
    from embody.retarget import retarget, shape_fit
    from embody.retarget.verify import verify
    from embody.robot import load_robot

    cfg = build_config(config_files, sets + ((f"robot.name={robot_name}",) if robot_name else ()))
    motion = load(in_path, limits=cfg.io)
    robot = load_robot(cfg.robot)
    body = load_body_model(cfg.body)
    fit = shape_fit(robot, body, cfg.ik)
    targets, solution = retarget(motion, robot, body, fit, cfg.ik)
    _, metrics = verify(robot, solution, targets)
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, q=solution.q.astype(np.float32), joint_names=np.array(solution.joint_names),
             fps=np.float64(solution.fps), q_control=solution.q_control.astype(np.float32),
             dt=np.float64(1.0 / solution.control_rate_hz), robot=np.array(robot.name),
             metrics=np.array(json.dumps(metrics, sort_keys=True)),
             **{f"frame_{k}": v for k, v in solution.frame_metrics.items()})
    summary = {"input": str(in_path), "output": str(out), "robot": robot.name, "frames": motion.num_frames,
               "shape_fit_mm": round(fit.mean_residual_mm, 2), **{k: round(v, 4) for k, v in metrics.items()}}
    if as_json:
        emit_json(summary)
    else:
        click.echo(f"{out}: {robot.name}, {motion.num_frames} frames, wrist {metrics['wrist_pos_err_mm']:.1f} mm, "
                   f"{metrics['wrist_rot_err_deg']:.1f} deg, self-collision frames "
                   f"{int(metrics['self_collision_frames'])}")
    return 0
