"""The paper's collision metrics (per sequence) and its Tables I and II (per dataset)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

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


def _colliding(df: pd.DataFrame) -> pd.DataFrame:
    return df[~df["no_collision"].astype(bool)]


def table1(df: pd.DataFrame) -> pd.DataFrame:
    """Table I: energy before/after, improved n/N, reduction, Pose MSE, ΔAccel, runtime.

    Statistics are over sequences that collided before; `no collision` counts the others.
    """
    c = _colliding(df)
    n, k = len(c), int(c["improved"].sum()) if len(c) else 0
    rows = [
        ("Sequences (colliding / total)", f"{n} / {len(df)}"),
        ("No collision", int(df["no_collision"].astype(bool).sum())),
        ("L_col before (mean)", c["energy_before"].mean()),
        ("L_col before (median)", c["energy_before"].median()),
        ("L_col after (mean)", c["energy_after"].mean()),
        ("L_col after (median)", c["energy_after"].median()),
        ("Improved n/N (%)", f"{k}/{n} ({100.0 * k / n if n else float('nan'):.1f}%)"),
        ("Reduction (median, %)", c["reduction_pct"].median()),
        ("Reduction (mean, %)", c["reduction_pct"].mean()),
        ("Pose MSE (median)", c["pose_mse"].median()),
        ("ΔAccel MSE (median)", c["daccel_mse"].median()),
        ("Runtime (mean, s)", df["runtime_s"].mean()),
    ]
    rows += depth_rows(df)
    return pd.DataFrame(rows, columns=["metric", "value"]).set_index("metric")


#: Mesh penetration depth columns (`embody.collision.depth.depth_metrics`) → Table I rows.
DEPTH_ROWS = (("frames_over_2mm", "Frames deeper than 2 mm ({})", "sum"),
              ("frames_over_5mm", "Frames deeper than 5 mm ({})", "sum"),
              ("max_depth_mm", "Max depth mm ({})", "max"),
              ("median_depth_mm", "Median depth mm of penetrating frames ({})", "median"))


def depth_rows(df: pd.DataFrame) -> list[tuple[str, object]]:
    """Depth rows before/after over all sequences: frame counts summed, the max of maxima, the
    median over sequences that penetrate of their per-sequence medians."""
    rows: list[tuple[str, object]] = []
    for key, label, how in DEPTH_ROWS:
        for tag in ("before", "after"):
            col = f"{key}_{tag}"
            if col not in df:
                continue
            v = df[col].astype(float)
            if how == "sum":
                value: object = int(v.sum())
            elif how == "max":
                value = float(v.max())
            else:
                pos = v[v > 0]
                value = float(pos.median()) if len(pos) else 0.0
            rows.append((label.format(tag), value))
    return rows


def table2(settings: Mapping[str, pd.DataFrame]) -> pd.DataFrame:
    """Table II (ablation): per setting N, success %, median reduction %, medians, mean time."""
    rows = []
    for name, df in settings.items():
        c = _colliding(df)
        n = len(c)
        rows.append({"setting": name, "N": n,
                     "Succ. (%)": 100.0 * c["improved"].sum() / n if n else float("nan"),
                     "Red. (%)": c["reduction_pct"].median(),
                     "Pose MSE": c["pose_mse"].median(),
                     "ΔAccel MSE": c["daccel_mse"].median(),
                     "Time (s)": df["runtime_s"].mean()})
    return pd.DataFrame(rows).set_index("setting")
