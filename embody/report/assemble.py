"""Tables I–III and the flat summary, aggregated from the run's stored per-sequence metrics.

The numbers come from `embody.metrics.tables` (`table1/table2`, which `embody.collision.metrics`
re-exports, and `critic_table`, the stored-row form of `embody.critic.refine_table`). This module only lays them out the paper's way (Before/After columns,
the paper's row names), adds the paper's reported figures as a separate column, and reads the
summary back out of the tables, so README, `summary.json` and the tables cannot disagree.
"""

from __future__ import annotations

import math
import re
from typing import Any

import pandas as pd

from embody.report.data import RunData
from embody.report.definitions import PAPER
from embody.report.tables import Table

PAPER_COLUMN = "Paper (reported)"
#: Table I rows in the paper's order.
TABLE1_ROWS = (
    "Collision energy (mean)", "Collision energy (median)", "Improved sequences (%)",
    "Collision reduction (median)", "Collision reduction (mean)",
    "Pose MSE vs. original (median)", "ΔAccel MSE (median)", "Runtime per sequence (mean)",
)
#: The paper's own Table I figures; rows it does not report stay blank (never invented).
PAPER_TABLE1 = {
    "Improved sequences (%)": 88.9,
    "Collision reduction (median)": 21.66,
    "Pose MSE vs. original (median)": 6.8e-4,
    "Runtime per sequence (mean)": 521.7,
}
#: Table II settings: which of the collision loss's regularisers are on (λ_close, λ_smooth).
ABLATION_SETTINGS = {
    "Collision only": (False, False),
    "+ Closeness": (True, False),
    "+ Closeness + Smoothness": (True, True),
}
#: Table III columns: header → `refine_table` column (scaled) or validation counter.
TABLE3_FROM_REFINE = {
    "Wrist pos. mean (mm)": ("wrist_mm_mean", 1.0),
    "Wrist pos. p95 (mm)": ("wrist_mm_p95", 1.0),
    "Wrist rot. mean (deg)": ("wrist_deg_mean", 1.0),
    "DTW wrist (mm)": ("wrist_dtw_mm", 1.0),
    "Rounds": ("rounds", 1.0),
    "Accepted (%)": ("accepted", 100.0),
}
#: Validation counters, summed over sequences: header → IK metric key.
TABLE3_COUNTS = {
    "Limit viol.": "joint_limit_violations",
    "Vel. viol.": "velocity_violations",
    "Self-coll. frames": "self_collision_frames",
}
#: Table III fidelity columns: header → `embody.metrics.fidelity` aggregate, stored by the
#: metrics step as `fidelity.<row>.<key>` (row: ik, preserving, refined).
TABLE3_FIDELITY = {
    "Location err. (mm)": "location_err_mm",
    "Location err. (scale)": "location_err",
    "Location agree (%)": "location_agree_pct",
    "Palm orient. (deg)": "palm_deg",
    "Handshape err.": "handshape_err",
    "Movement DTW (scale)": "movement_dtw",
    "Contact F1": "contact_f1",
}
TABLE3_KEYS = {
    "Location err. (mm)": "location_err_mm", "Location err. (scale)": "location_err",
    "Location agree (%)": "location_agree_pct", "Palm orient. (deg)": "palm_deg",
    "Handshape err.": "handshape_err", "Movement DTW (scale)": "movement_dtw",
    "Contact F1": "contact_f1",
    "Wrist pos. mean (mm)": "wrist_pos_mean_mm", "Wrist pos. p95 (mm)": "wrist_pos_p95_mm",
    "Wrist rot. mean (deg)": "wrist_rot_mean_deg", "DTW wrist (mm)": "wrist_dtw_mm",
    "Limit viol.": "limit_violations", "Vel. viol.": "velocity_violations",
    "Self-coll. frames": "self_collision_frames", "Rounds": "rounds",
    "Accepted (%)": "accepted_pct", "N": "n",
}
#: Table III's physics column group (the exported array of the final row replayed in MuJoCo by
#: the `physics` step): header → (physics metric, how sequences are pooled).
TABLE3_PHYSICS = {
    "Physics-valid (%)": ("valid", "pct"),
    "Torque > limit (samples)": ("torque_over_samples", "sum"),
    "Peak torque/limit": ("torque_ratio_max", "max"),
    "Saturated steps (%)": ("saturated_steps", "steps_pct"),
    "Palm p95 sim. (mm)": ("palm_err_p95_mm", "mean"),
    "Sim. self-contacts": ("sim_contact_samples", "sum"),
    "ZMP margin min (mm)": ("zmp_margin_min_mm", "min"),
    "Stays up standing (%)": ("standing_holds", "pct"),
    "Location err. sim. (mm)": ("fidelity.location_err_mm", "mean"),
}
#: summary.json key (under `physics.`) of each TABLE3_PHYSICS column.
PHYSICS_SUMMARY = {
    "Physics-valid (%)": "valid_pct", "Torque > limit (samples)": "torque_over_samples",
    "Peak torque/limit": "torque_ratio_max", "Saturated steps (%)": "saturated_step_pct",
    "Palm p95 sim. (mm)": "palm_p95_mm", "Sim. self-contacts": "sim_contact_samples",
    "ZMP margin min (mm)": "zmp_margin_min_mm", "Stays up standing (%)": "standing_ok_pct",
    "Location err. sim. (mm)": "location_err_mm",
}
_NUMBER = re.compile(r"[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?")


def number(cell: Any) -> float:
    """A cell as a float: numbers as they are, "8/9 (88.9%)" → 88.9, blanks → NaN."""
    if cell is None or cell is pd.NA:
        return math.nan
    if isinstance(cell, (int, float)):
        return float(cell)
    text = str(cell)
    inner = re.search(r"\(([^)]*)\)", text)
    found = _NUMBER.findall(inner.group(1) if inner else text)
    return float(found[-1]) if found else math.nan


def table1_slot(label: str) -> tuple[str, str]:
    """Where a row of `collision.metrics.table1` goes: (paper row name, "Before"|"After")."""
    low = label.lower()
    if "depth" in low or "deeper" in low:  # mesh penetration depth rows: "<row> (before|after)"
        row, _, tag = label.rpartition(" (")
        return row, "Before" if tag.startswith("before") else "After"
    stat = "median" if "median" in low else "mean"
    if "l_col" in low or "energy" in low:
        return f"Collision energy ({stat})", "Before" if "before" in low else "After"
    if "improved" in low:
        return "Improved sequences (%)", "After"
    if "reduction" in low:
        return f"Collision reduction ({stat})", "After"
    if "pose" in low:
        return "Pose MSE vs. original (median)", "After"
    if "accel" in low:
        return "ΔAccel MSE (median)", "After"
    if "runtime" in low:
        return "Runtime per sequence (mean)", "After"
    return label, "After"


def table1(data: RunData) -> Table:
    """Table I: the library's `table1` values in Before/After columns, plus the paper's."""
    from embody.metrics.tables import table1 as collision_table1

    lib = collision_table1(data.collision)
    cells: dict[str, dict[str, Any]] = {}
    for label, value in lib.iloc[:, 0].items():
        row, column = table1_slot(str(label))
        cells.setdefault(row, {})[column] = value
    order = [r for r in cells if r not in TABLE1_ROWS] + [r for r in TABLE1_ROWS if r in cells]
    frame = pd.DataFrame({
        "Metric": order,
        "Before": [cells[r].get("Before") for r in order],
        "After": [cells[r].get("After") for r in order],
        PAPER_COLUMN: [PAPER_TABLE1.get(r) for r in order],
    })
    return Table("table1_collision", "Table I: self-collision mitigation (SMPL-X)", frame, cite=PAPER["key"])


def table2(data: RunData) -> Table:
    """Table II over the ablation settings, or the run's own setting alone without `--ablation`."""
    from embody.metrics.tables import table2 as collision_table2

    settings = data.ablation or {"This run": data.collision}
    frame = collision_table2(settings).reset_index()
    frame = frame.rename(columns={frame.columns[0]: "Setting"})
    return Table("table2_ablation", "Table II: loss-term ablation", frame, cite=PAPER["key"])


def _counts(frame: pd.DataFrame) -> dict[str, float]:
    return {h: float(frame[k].sum()) if k in frame else math.nan
            for h, k in TABLE3_COUNTS.items()}


def _fidelity(data: RunData, row: str) -> dict[str, float]:
    """Mean fidelity of one Table III row over sequences; contact F1 pooled over all frames."""
    frame = data.other.get("metrics", pd.DataFrame())
    out: dict[str, float] = {}
    for header, key in TABLE3_FIDELITY.items():
        col = f"fidelity.{row}.{key}"
        values = pd.to_numeric(frame[col], errors="coerce") if col in frame else pd.Series(dtype=float)
        out[header] = float(values.mean()) if values.notna().any() else math.nan
    cols = [f"fidelity.{row}.contact_{k}" for k in ("tp", "frames_human", "frames_robot")]
    if all(c in frame for c in cols):
        tp, hp, rp = (float(pd.to_numeric(frame[c], errors="coerce").sum()) for c in cols)
        p, r = (tp / rp if rp else math.nan), (tp / hp if hp else math.nan)
        out["Contact F1"] = 2 * p * r / (p + r) if rp and hp and p + r > 0 else (0.0 if rp or hp else math.nan)
    return out


def _baseline_counts(data: RunData) -> dict[str, float]:
    frame = data.other.get("metrics", pd.DataFrame())
    return {h: float(pd.to_numeric(frame[f"fidelity.ik.{k}"], errors="coerce").sum())
            if f"fidelity.ik.{k}" in frame else math.nan for h, k in TABLE3_COUNTS.items()}


def physics_figures(data: RunData) -> dict[str, float]:
    """TABLE3_PHYSICS over the run's sequences (NaN where the physics step did not run)."""
    frame = data.other.get("physics", pd.DataFrame())
    out: dict[str, float] = {}
    for header, (key, pool) in TABLE3_PHYSICS.items():
        if key not in frame:
            out[header] = math.nan
            continue
        values = pd.to_numeric(frame[key].map(lambda v: float(v) if isinstance(v, (bool, int, float)) else v),
                               errors="coerce").dropna()
        if values.empty:
            out[header] = math.nan
        elif pool == "pct":
            out[header] = 100.0 * float(values.mean())
        elif pool == "sum":
            out[header] = float(values.sum())
        elif pool == "max":
            out[header] = float(values.max())
        elif pool == "min":
            out[header] = float(values.min())
        elif pool == "steps_pct" and "control_steps" in frame:
            steps = float(pd.to_numeric(frame["control_steps"], errors="coerce").sum())
            out[header] = 100.0 * float(values.sum()) / steps if steps else math.nan
        else:
            out[header] = float(values.mean())
    return out


def table3(data: RunData) -> Table:
    """IK-only vs refined (one row per critic) from `critic_table`, plus validation counts.

    Without a critic only the IK-only row is filled, from the IK's own aggregate metrics (its
    targets are the reference then); columns that need the critic's metrics stay blank.
    """
    from embody.metrics.tables import critic_table

    rows = []
    ik_counts = _counts(data.retarget)
    if not data.refined:
        ik = data.retarget
        rows.append({"Method": "IK only",
                     "Wrist pos. mean (mm)": ik["wrist_pos_err_mm"].mean() if len(ik) else None,
                     "Wrist rot. mean (deg)": ik["wrist_rot_err_deg"].mean() if len(ik) else None,
                     **ik_counts, "N": len(ik)})
    for critic, refined_rows in sorted(data.refined.items()):
        lib = critic_table(data.critic_ik.get(critic, pd.DataFrame()), refined_rows)
        for label, row in lib.iterrows():
            refined = str(label).lower().startswith("refined")
            if not refined and rows:
                continue  # the IK-only row is the same for every critic
            counts = _counts(data.validation.get(critic, pd.DataFrame())) if refined else ik_counts
            rows.append({"Method": f"Refined ({critic})" if refined else "IK only",
                         **{h: row[k] * s for h, (k, s) in TABLE3_FROM_REFINE.items()},
                         **counts, "N": int(row["n"])})
    # Sign fidelity (the human as reference): with location-preserving targets the retarget step's
    # row is "Location-preserving" and the metrics step's plain shape-fit solve is "IK only".
    metrics = data.other.get("metrics", pd.DataFrame())
    preserving = "fidelity.preserving.location_err" in metrics
    for row in rows:
        if row["Method"] == "IK only":
            if preserving:
                row["Method"] = "Location-preserving"
            row.update(_fidelity(data, "preserving" if preserving else "ik"))
        else:
            row.update(_fidelity(data, "refined"))
    if preserving:
        rows.insert(0, {"Method": "IK only", **_fidelity(data, "ik"), **_baseline_counts(data),
                        "N": int(metrics["fidelity.ik.location_err"].notna().sum())})
    columns = ["Method", *TABLE3_FIDELITY, "Wrist pos. mean (mm)", "Wrist pos. p95 (mm)",
               "Wrist rot. mean (deg)", "DTW wrist (mm)", *TABLE3_COUNTS, "Rounds", "Accepted (%)", "N"]
    frame = pd.DataFrame(rows).reindex(columns=columns)
    return Table("table3_retargeting",
                 "Table III: retargeting fidelity, IK-only vs refined",
                 frame, cite=PAPER["key"])


def table3_physics(data: RunData) -> Table | None:
    """Table III's physics column group, as a table of its own beside it (Table III is already
    as wide as the page): the row of the final trajectory, whose exported array the physics step
    replays in MuJoCo, beside its kinematic location error. None when the run has no physics step."""
    physics = physics_figures(data)
    if all(math.isnan(v) for v in physics.values()):
        return None
    frame = data.other.get("physics", pd.DataFrame())
    t3 = table3(data)
    final = str(t3.frame["Method"].iloc[-1]) if len(t3.frame) else "final"
    row = {"Method": final, "Location err. (mm)": _cell(t3, final, "Location err. (mm)"), **physics,
           "N": int(len(frame))}
    return Table("table3_physics", "Table III (physics): the final trajectory replayed in MuJoCo "
                 "(fixed base and standing, the robot's gains and effort limits)",
                 pd.DataFrame([row], columns=["Method", "Location err. (mm)", *TABLE3_PHYSICS, "N"]))


#: The verdicts table's rows: label → `embody.verdicts` name.
VERDICT_ROWS = {"Processed ok": "processed_ok", "Export-valid": "export_valid",
                "Critic-accepted": "critic_accepted", "Physics-valid": "physics_valid"}


def verdicts_table(data: RunData) -> Table:
    """The report's first table: how many sequences hold each of the four verdicts."""
    per = data.verdicts()
    total = len(per)
    rows = []
    for label, name in VERDICT_ROWS.items():
        known = per[name].dropna() if name in per else pd.Series(dtype=object)
        n = int(known.astype(bool).sum()) if len(known) else None
        rows.append({"Verdict": label,
                     "Sequences": f"{n}/{total}" if n is not None else "n/a",
                     "Share (%)": 100.0 * n / total if n is not None and total else None})
    return Table("verdicts", "Verdicts: processed ok, export-valid, critic-accepted, physics-valid",
                 pd.DataFrame(rows, columns=["Verdict", "Sequences", "Share (%)"]))


def _row(table: Table, label: str) -> pd.Series | None:
    hits = table.frame[table.frame.iloc[:, 0].astype(str) == label]
    return None if hits.empty else hits.iloc[0]


def _cell(table: Table, label: str, column: str) -> float:
    row = _row(table, label)
    return math.nan if row is None or column not in row.index else number(row[column])


def summary(data: RunData, tables: dict[str, Table]) -> dict[str, Any]:
    """Flat `summary.json` keys, read from the tables (and the sequence statuses)."""
    out: dict[str, Any] = {
        "run": data.name,
        **({"robot": data.robot} if data.robot else {}),
        "sequences.total": int(len(data.sequences)),
        "sequences.ok": int((data.sequences["status"] == "ok").sum()),
        "sequences.failed": int((data.sequences["status"] != "ok").sum()),
    }
    from embody.verdicts import run_verdicts
    per = data.verdicts()
    counts = run_verdicts(per.to_dict("records"))
    out.update({f"verdicts.{k}": v for k, v in counts.items()})
    t1 = tables.get("table1_collision")
    if t1 is not None:
        for key, (row, col) in {
            "energy_mean_before": ("Collision energy (mean)", "Before"),
            "energy_mean_after": ("Collision energy (mean)", "After"),
            "energy_median_before": ("Collision energy (median)", "Before"),
            "energy_median_after": ("Collision energy (median)", "After"),
            "improved_pct": ("Improved sequences (%)", "After"),
            "reduction_median_pct": ("Collision reduction (median)", "After"),
            "reduction_mean_pct": ("Collision reduction (mean)", "After"),
            "pose_mse_median": ("Pose MSE vs. original (median)", "After"),
            "daccel_mse_median": ("ΔAccel MSE (median)", "After"),
            "runtime_mean_s": ("Runtime per sequence (mean)", "After"),
        }.items():
            out[f"collision.{key}"] = _cell(t1, row, col)
    t3 = tables.get("table3_retargeting")
    if t3 is not None:
        labels = [("IK only", "retarget.ik_only"), ("Location-preserving", "retarget.preserving")]
        labels += [(f"Refined ({c})", f"retarget.refined.{c}") for c in sorted(data.refined)]
        if data.refined:  # the first critic's row doubles as "the refined result"
            labels.append((f"Refined ({sorted(data.refined)[0]})", "retarget.refined"))
        for label, prefix in labels:
            for header, key in TABLE3_KEYS.items():
                out[f"{prefix}.{key}"] = _cell(t3, label, header)
        final = "retarget.refined" if data.refined else (
            "retarget.preserving" if _row(t3, "Location-preserving") is not None else "retarget.ik_only")
        for key in ("limit_violations", "velocity_violations", "self_collision_frames"):
            out[f"retarget.{key}"] = out[f"{final}.{key}"]
    for header, value in physics_figures(data).items():
        out[f"physics.{PHYSICS_SUMMARY[header]}"] = value
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in out.items()}
