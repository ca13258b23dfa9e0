"""The low-level command fields an exported npz carries, and the physics check of a file.

Per 50 Hz sample a Unitree `LowCmd` motor command takes q, q̇, a feed-forward torque, kp and kd.
The npz carries exactly these (`embody.physics.commands`): `q` (T,n), `qd` (T,n, rad/s, the slope of
the natural cubic spline through q: a (q, q̇) Hermite interpolator plays that spline), `tau_ff` (T,n,
N·m, fixed-base free-motion inverse dynamics of the spline at the samples),
`kp` (n, N·m/rad) and `kd` (n, N·m·s/rad) per joint, and `control_rate_hz` (the rate the gains
were published for). `embody export --check` replays each file in physics under the
physics-valid rule (`physics_check`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError

#: The npz fields beside `q` (per sample or per joint).
CONTROL_FIELDS = ("qd", "tau_ff", "kp", "kd", "control_rate_hz")
#: What `physics_check` reports per file.
PHYSICS_CHECK_KEYS = ("physics_valid", "torque_over_samples", "saturated_steps", "palm_err_p95_mm",
                      "sim_contact_samples", "zmp_margin_min_mm", "standing_holds")


def control_fields(robot: Any, q: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """The command arrays for joint samples q (T,n) taken every `dt` s on `robot`."""
    from embody.physics import actuation, commands
    cmd = commands(robot, q, 1.0 / dt)
    return {"qd": cmd.qd, "tau_ff": cmd.tau_ff, "kp": cmd.kp, "kd": cmd.kd,
            "control_rate_hz": np.float64(actuation(robot).control_rate_hz)}


def file_commands(robot: Any, path: Path, q: np.ndarray, dt: float) -> Any:
    """The commands a file carries (npz with the control fields), else those of its q."""
    from embody.physics import Commands, commands
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                fields = {k: np.asarray(z[k], dtype=np.float64) for k in ("qd", "tau_ff", "kp", "kd") if k in z.files}
        except Exception as exc:  # zipfile and numpy raise many types on a corrupt member
            raise InputError(path, None, f"cannot read npz: {type(exc).__name__}: "
                                         f"{' '.join(str(exc).split())[:200]}") from None
        if len(fields) == 4:
            n = robot.n_joints
            for key, shape in (("qd", q.shape), ("tau_ff", q.shape), ("kp", (n,)), ("kd", (n,))):
                if fields[key].shape != shape:
                    raise InputError(path, key, f"expected shape {shape}, got {fields[key].shape}")
                if not np.isfinite(fields[key]).all():
                    raise InputError(path, key, "contains non-finite values (NaN or inf)")
            return Commands(fps=1.0 / dt, q=q, **fields)
    return commands(robot, q, 1.0 / dt)


def physics_check(robot: Any, path: Path, q: np.ndarray, dt: float) -> dict[str, Any]:
    """The physics-valid rule on a file: its commands replayed in MuJoCo (`embody.physics`).
    A file whose gains are not the robot's fails (its replay would test other motors)."""
    from embody.physics import actuation, evaluate
    cmd = file_commands(robot, path, q, dt)
    act = actuation(robot)
    if not (np.allclose(cmd.kp, act.kp) and np.allclose(cmd.kd, act.kd)):
        return {"physics_valid": False, "physics_error": "kp/kd differ from the robot's actuation"}
    m = evaluate(robot, q, 1.0 / dt, cmd=cmd).metrics
    out = {k: m.get(k) for k in PHYSICS_CHECK_KEYS if k != "physics_valid"}
    return {"physics_valid": bool(m["valid"]), **out, "physics_error": ""}
