"""A stored run's trajectories as `embody export` writes them (the run's robot loaded here).

The exported array of each sequence is the one the metrics step stored (`q_control`) with its
validation counters and its samples' source times (`source_time`: the array may be retimed,
`retarget.dynamics_limits`; written into the npz); runs made before the metrics step stored them get it built now with the
same function (`retarget.control.control_trajectory`) and validated here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from embody.errors import InputError
from embody.report.reader import METRICS, REFINE, RETARGET, open_run, run_config, sequence_text

__all__ = ["exported_trajectory", "load_result", "run_robot", "run_trajectories"]


def load_result(store: Any, seq: dict[str, Any], step: str) -> Any:
    """The stored result of `step` for one manifest sequence entry, as the stage's own type."""
    from embody.tasks.stages import COLLIDE as C, REFINE as R, RENDER as V, RETARGET as T, SOURCE as S

    loader = {s.name: s.load for s in (S, C, T, R, V)}[step]
    art = store.read(step, seq["steps"][step])
    return loader(art.arrays, art.attrs)


def exported_trajectory(store: Any, robot: Any, seq: dict[str, Any], ik: Any,
                        q: np.ndarray) -> tuple[np.ndarray, dict[str, float], np.ndarray]:
    """The control-rate array `embody export` writes for a sequence, its validation counters
    and each sample's source time (s; `retarget.dynamics_limits`: the array may be retimed)."""
    from embody.retarget.control import control_trajectory_checked
    from embody.retarget.dynamics_limits import uniform_time
    from embody.retarget.validation import VALIDATION_KEYS, validation_counts

    stored = seq.get("metrics", {}).get(METRICS, {})
    if METRICS in seq.get("steps", {}) and "validation_rate_hz" in stored:
        art = store.read(METRICS, seq["steps"][METRICS])
        if "q_control" in art.arrays:
            q_control = np.asarray(art.arrays["q_control"])
            times = art.arrays.get("source_time")
            return (q_control, {k: float(stored[k]) for k in VALIDATION_KEYS},
                    uniform_time(len(q_control), ik.control_rate_hz) if times is None else np.asarray(times))
    q_control, _, times = control_trajectory_checked(robot, q, ik.fps, ik.control_rate_hz)
    return q_control, validation_counts(robot, q_control, ik.control_rate_hz), times


def run_robot(store_root: Any, run: str) -> Any:
    """The robot `run` was retargeted for, as its recorded config loads it."""
    from embody.robot import load_robot

    return load_robot(run_config(open_run(store_root, run)[1]).robot)


def run_trajectories(store_root: Any, run: str, robot_name: str
                     ) -> tuple[list[Any], list[tuple[str, str]]]:
    """The exported (control-rate) trajectory of every finished sequence of `run` (from the
    refined one when the critic ran) with its stored validation counters, and (id, reason) of
    the sequences the run itself failed."""
    from embody.export.library import Trajectory
    from embody.robot import load_robot

    store, manifest = open_run(store_root, run)
    cfg = run_config(manifest)
    if cfg.robot.name != robot_name:
        raise InputError(manifest.path, "robot", f"run {run!r} was retargeted for "
                         f"{cfg.robot.name!r}, not {robot_name!r}")
    robot = None
    out, failed = [], []
    for sid, seq in sorted(manifest.sequences.items()):
        if seq["status"] != "ok" or RETARGET not in seq["steps"]:
            failed.append((sid, f"run {seq['status']}: {seq.get('error') or 'not retargeted'}"))
            continue
        ik = load_result(store, seq, RETARGET)
        if REFINE in seq["steps"]:
            final = load_result(store, seq, REFINE)
            q = np.asarray(final.q, dtype=np.float64)
            scores = {**final.final.metrics, "refined": True, "accepted": bool(final.accepted)}
        else:
            q = np.asarray(ik.q, dtype=np.float64)
            scores = {"wrist_mm_mean": ik.metrics.get("wrist_pos_err_mm"),
                      "wrist_deg_mean": ik.metrics.get("wrist_rot_err_deg"), "refined": False}
        stored = seq.get("metrics", {}).get(METRICS, {})
        if robot is None and "validation_rate_hz" not in stored:  # an old run: build it here
            robot = load_robot(cfg.robot)
        q_control, counts, times = exported_trajectory(store, robot, seq, ik, q)
        validation = {**scores, **counts, "fps": ik.fps, "control_rate_hz": ik.control_rate_hz,
                      **{k: stored[k] for k in ("time_stretch_max", "duration_ratio") if k in stored}}
        out.append(Trajectory(id=sid, robot=robot_name, joint_names=tuple(ik.joint_names),
                              q=q_control, dt=1.0 / ik.control_rate_hz, text=sequence_text(store, seq),
                              validation=validation, source_time=times))
    return out, failed
