"""`embody play`: render an exported trajectory back to an animated preview (MuJoCo offscreen),
or play it in MuJoCo's interactive viewer (`--viewer`, needs a display)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import click
import numpy as np

from embody.cli.common import build_config, config_options
from embody.errors import InputError, UsageError


def has_display() -> bool:
    """Whether a window can open: always on macOS and Windows, else X11 or Wayland must be set."""
    if sys.platform == "darwin" or sys.platform.startswith("win"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def run_viewer(robot, q: np.ndarray, dt: float) -> None:
    """Loop the trajectory in MuJoCo's passive viewer, in real time, until the window closes."""
    import mujoco
    import mujoco.viewer

    model = robot.model
    data = mujoco.MjData(model)
    with mujoco.viewer.launch_passive(model, data) as viewer:
        step = 0
        while viewer.is_running():
            start = time.monotonic()
            data.qpos[:] = robot.qpos(q[step % len(q)])
            mujoco.mj_forward(model, data)
            viewer.sync()
            step += 1
            time.sleep(max(0.0, dt - (time.monotonic() - start)))


def preview_frames(num_steps: int, dt: float, preview_fps: float, max_frames: int) -> np.ndarray:
    """Control steps to render: `preview_fps` per second of motion, at most `max_frames`."""
    duration = num_steps * dt
    count = int(np.clip(round(duration * preview_fps), 2, min(max_frames, num_steps)))
    return np.unique(np.linspace(0, num_steps - 1, count).round().astype(np.int64))


def physics_replay(robot, path: Path, q: np.ndarray, dt: float) -> np.ndarray:
    """The simulated joints of the file's physics replay (fixed base) at its samples; prints
    the physics-valid figures of the file (as `embody export --check` judges it)."""
    from embody.export.control import file_commands
    from embody.physics import evaluate

    if robot.spec.actuation is None:
        raise InputError(path, "robot", f"{robot.name} has no actuation section: no physics replay")
    result = evaluate(robot, q, 1.0 / dt, cmd=file_commands(robot, path, q, dt))
    m = result.metrics
    click.echo(f"physics: {'valid' if m['valid'] else 'NOT valid'} · torque over limit "
               f"{m['torque_over_samples']} samples · saturated {m['saturated_step_pct']:.1f} % of steps · "
               f"palm p95 {m.get('palm_err_p95_mm', float('nan')):.1f} mm · sim contacts "
               f"{m['sim_contact_samples']} · ZMP min {m['zmp_margin_min_mm']:.0f} mm · standing "
               f"{'holds' if m['standing_holds'] else 'falls'}")
    return np.asarray(result.arrays["q_sim"])


@click.command("play")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", type=click.Path(dir_okay=False),
              help="Preview path; the suffix follows the format [default: FILE's name + format].")
@click.option("--format", "fmt", type=click.Choice(["mp4", "gif", "webp"]), default=None,
              help="Preview format [default: render.preview_format, mp4].")
@click.option("--viewer", is_flag=True,
              help="Play in MuJoCo's interactive viewer instead (needs a display).")
@click.option("--physics", is_flag=True,
              help="Show the physics replay instead: the file's commands (q, q̇, feed-forward "
                   "torque, kp/kd) played in MuJoCo with the pelvis welded, and its figures.")
@config_options
def command(file: str, out: str | None, fmt: str | None, viewer: bool, physics: bool,
            config_files: tuple[str, ...], sets: tuple[str, ...]) -> int:
    """Render FILE (an `embody export` .npz) on its robot as an animated preview, or play it in
    MuJoCo's interactive viewer with `--viewer`; `--physics` shows its physics replay."""
    if viewer and not has_display():
        raise UsageError("--viewer needs a display, and none is set (DISPLAY / WAYLAND_DISPLAY); "
                         "run without --viewer to write a preview file instead")
    from embody.render import SceneRenderer, write_preview
    from embody.export.library import Trajectory
    from embody.robot import load_robot

    cfg = build_config(config_files, sets)
    traj = Trajectory.load(file)
    robot = load_robot(cfg.robot.model_copy(update={"name": traj.robot}))
    missing = sorted(set(traj.joint_names) - set(robot.joint_names))
    if missing:
        raise InputError(file, "joint_names", f"not joints of {traj.robot}: {missing[:5]}")
    q = np.tile(robot.tpose, (len(traj.q), 1))
    q[:, [robot.joint_index(n) for n in traj.joint_names]] = traj.q
    if physics:
        q = physics_replay(robot, Path(file), q, traj.dt)
    if viewer:
        run_viewer(robot, q, traj.dt)
        return 0
    rate = cfg.render.preview_fps or 1.0 / traj.dt  # null: every step, in real time
    steps = preview_frames(len(q), traj.dt, rate, cfg.render.preview_max_frames)
    fmt = fmt or (cfg.render.preview_format if cfg.render.preview_format != "none" else "mp4")
    with SceneRenderer(robot, cfg.render, torso_body=robot.spec.torso_body) as renderer:
        frames = renderer.robot_frames(q[steps], cfg.render.views[0])
    target = Path(out) if out else Path(file).with_suffix("")
    written = write_preview(frames, target, len(steps) / (len(q) * traj.dt), fmt)
    click.echo(f"preview: {written} ({len(steps)} frames)")
    return 0
