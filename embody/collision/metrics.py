"""The paper's collision metrics (per sequence); its Tables I and II (per dataset) live in the
torch-free `embody.metrics.tables` (the report reads them) and are re-exported here."""

from __future__ import annotations

import numpy as np

from embody.metrics.tables import DEPTH_ROWS, depth_rows, table1, table2  # noqa: F401

#: Keeps the reduction finite when the energy before is zero.
EPS = 1e-12


def pose_mse(x: np.ndarray, x0: np.ndarray) -> float:
    """(1/T) Σ_t ‖x_t − x0_t‖² over the flattened axis-angle pose."""
    t = x.shape[0]
    return float(((x - x0).reshape(t, -1) ** 2).sum(1).mean())


def accel_mse(x: np.ndarray) -> float:
    """Mean over frames of the squared second difference ‖x_{t+1} − 2x_t + x_{t−1}‖²."""
    t = x.shape[0]
    if t < 3:
        return 0.0
    acc = (x[2:] - 2.0 * x[1:-1] + x[:-2]).reshape(t - 2, -1)
    return float((acc ** 2).sum(1).mean())


def reduction_pct(before: float, after: float) -> float:
    return float((before - after) / (abs(before) + EPS) * 100.0)


def sequence_metrics(x0: np.ndarray, x: np.ndarray, energy_before: float, energy_after: float,
                     runtime_s: float, steps: int) -> dict[str, float | int | bool]:
    """One row of the per-sequence table; `no_collision` rows are neither success nor failure."""
    x0 = np.asarray(x0, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    no_collision = energy_before <= 0.0
    return {
        "energy_before": float(energy_before), "energy_after": float(energy_after),
        "improved": bool(energy_after < energy_before), "no_collision": bool(no_collision),
        "reduction_pct": 0.0 if no_collision else reduction_pct(energy_before, energy_after),
        "pose_mse": pose_mse(x, x0), "daccel_mse": accel_mse(x) - accel_mse(x0),
        "runtime_s": float(runtime_s), "steps": int(steps), "frames": int(x.shape[0]),
    }
