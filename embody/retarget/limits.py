"""Joint and velocity limits: hard by construction, then a feasibility pass at the trajectory's fps."""

from __future__ import annotations

import numpy as np

#: Distance (m) the exported control-rate array keeps between every counted pair of bodies (its
#: contact repair pushes closer pairs apart, the torque/ZMP retiming checks and clears the samples it adds): the
#: physics replay at the robot's real gains tracks each joint to ~1°, which closed the gap of a
#: counted pair by up to 1.87 mm on the default G1 run (`benchmarks/physics.py`,
#: `replay_closure_max_mm`), so a narrower exported gap touches on the robot.
EXPORT_GAP = 0.002
#: How far past `EXPORT_GAP` (m) the repair pushes a pair it moves: a linearised push that
#: aims at the gap itself lands a hair short of it.
EXPORT_GAP_PUSH = 0.0005


def clamp_velocity(q: np.ndarray, vmax: np.ndarray, fps: float) -> np.ndarray:
    """Limit every per-step change to vmax/fps (one forward pass).

    Each step moves towards a value inside the joint box, so box limits are preserved.
    """
    step = np.asarray(vmax / fps, dtype=np.float64)
    out = np.array(q, dtype=np.float64)
    rows, lo, d = list(out), -step, np.empty_like(step)  # row views: no per-step indexing
    for t in range(1, len(rows)):
        np.subtract(rows[t], rows[t - 1], out=d)
        np.minimum(np.maximum(d, lo, out=d), step, out=d)  # = np.clip, without its overhead
        np.add(rows[t - 1], d, out=rows[t])
    return out


def velocity_violations(q: np.ndarray, vmax: np.ndarray, fps: float, tol: float = 1e-9) -> int:
    """Number of (step, joint) pairs whose speed exceeds its limit."""
    if len(q) < 2:
        return 0
    return int((np.abs(np.diff(q, axis=0)) * fps > vmax * (1 + tol) + tol).sum())


def limit_violations(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, tol: float = 1e-9) -> int:
    return int(((q < lower - tol) | (q > upper + tol)).sum())


def resample(q: np.ndarray, fps: float, rate: float) -> np.ndarray:
    """Linear resampling to `rate` Hz over the same duration; never exceeds the source speeds."""
    t_src = np.arange(len(q)) / fps
    n = int(np.floor(t_src[-1] * rate + 1e-9)) + 1
    t_dst = np.arange(n) / rate
    return np.stack([np.interp(t_dst, t_src, q[:, j]) for j in range(q.shape[1])], axis=1)
