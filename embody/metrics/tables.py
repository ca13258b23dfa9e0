"""The paper's dataset tables from per-sequence metric rows (pandas only, no torch).

Table I and II aggregate the collision step's per-sequence metrics; `critic_table` aggregates
the critic's per-sequence metrics of the IK-only and the final round. The report reads stored
rows and calls these; the stages' own modules re-export them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

__all__ = ["CRITIC_METRICS", "DEPTH_ROWS", "critic_table", "depth_rows", "table1", "table2"]


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


#: The critic's per-round wrist metrics averaged in `critic_table` (as `critic.refine_table`).
CRITIC_METRICS = ("wrist_mm_mean", "wrist_mm_p95", "wrist_deg_mean", "wrist_deg_p95",
                  "wrist_dtw_mm", "wrist_offset_arm")


def critic_table(ik_only: pd.DataFrame, refined: pd.DataFrame) -> pd.DataFrame:
    """"IK-only vs refined" from stored per-sequence rows: `ik_only` has the critic's metrics of
    its IK-only round (and `accepted`), `refined` those of the final round plus `accepted` and
    `rounds`. Means over the refined sequences (the IK-only row over those of them that have
    IK-only rows; all of them in a current run): the same numbers as `critic.refine_table`."""
    ids = refined.index
    rows = {}
    for label, frame in (("IK-only", ik_only.loc[ik_only.index.intersection(ids)]), ("refined", refined)):
        row = {m: float(pd.to_numeric(frame[m], errors="coerce").mean()) if m in frame else np.nan
               for m in CRITIC_METRICS}
        row["accepted"] = float(frame["accepted"].astype(bool).mean()) if "accepted" in frame and len(frame) else np.nan
        row["rounds"] = float(pd.to_numeric(frame["rounds"]).mean()) if label == "refined" and "rounds" in frame else 0.0
        row["n"] = len(frame)
        rows[label] = row
    return pd.DataFrame.from_dict(rows, orient="index")
