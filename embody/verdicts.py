"""The four verdicts on a sequence: processed ok, export-valid, critic-accepted, physics-valid.

"Success" means three different things, so every place that counts it (the run's closing
summary, `summary.json`, the report's first table and `embody export`) asks this module, and
they cannot disagree. NumPy-free and torch-free on purpose: the run's closing summary uses it.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

__all__ = ["VALIDATION_KEYS", "VERDICTS", "PHYSICS_RULE", "export_valid", "in_default_export",
           "physics_valid", "plural", "run_verdicts", "sequence_verdicts", "verdict_line", "violations"]

#: Validation counters (from `embody.retarget.validation.validation_counts`) that must all be
#: zero for a trajectory to be exported: joint-limit violations, velocity-limit violations,
#: MuJoCo self-collision frames and inverse-dynamics torques over the motors' effort limits.
VALIDATION_KEYS = ("joint_limit_violations", "velocity_violations", "self_collision_frames", "torque_viol")
#: Verdict name → what it means (the report prints these definitions).
VERDICTS = {
    "processed_ok": "every pipeline step finished without an error",
    "export_valid": "processed ok and its final trajectory has zero joint-limit violations, "
                    "zero velocity-limit violations, zero MuJoCo self-collision frames and "
                    "no inverse-dynamics torque over a motor's effort limit (the rule `embody export` applies)",
    "critic_accepted": "the critic accepted the final round (blank when the run had no critic)",
    "physics_valid": "processed ok and its exported trajectory, replayed in MuJoCo with the robot's "
                     "gains and effort limits, has zero samples over a torque limit, zero saturated "
                     "control steps, palm tracking p95 ≤ 10 mm, zero self-contacts in simulation, the "
                     "ZMP ≥ 20 mm inside the feet at every sample, and the robot stays up standing",
}

#: The physics-valid rule on the `physics` step's metrics: key → (comparison, bound).
PHYSICS_RULE: dict[str, tuple[str, float]] = {
    "torque_over_samples": ("==", 0.0),
    "saturated_steps": ("==", 0.0),
    "palm_err_p95_mm": ("<=", 10.0),
    "sim_contact_samples": ("==", 0.0),
    "zmp_margin_min_mm": (">=", 20.0),
    "standing_holds": ("==", 1.0),
}


def physics_valid(physics: Mapping[str, Any]) -> bool:
    """The physics-valid rule (PHYSICS_RULE) on one sequence's `physics` metrics; a missing or
    non-finite figure fails it. A robot without fingers or palms has no palm figure: only the
    rows it measures are read (a missing palm p95 on a robot without palms reads as 0 mm)."""
    for key, (op, bound) in PHYSICS_RULE.items():
        value = physics.get(key)
        if value is None and key == "palm_err_p95_mm" and physics.get("palm_landmarks") == 0:
            continue
        try:
            number = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            return False
        if not math.isfinite(number):
            return False
        if (op == "==" and number != bound) or (op == "<=" and number > bound) or (op == ">=" and number < bound):
            return False
    return True


def violations(counters: Mapping[str, Any]) -> dict[str, Any]:
    """The non-zero (or missing / non-finite) counters among VALIDATION_KEYS; empty = valid.

    This is the export rule: a counter that was never measured is not evidence of validity.
    """
    out: dict[str, Any] = {}
    for key in VALIDATION_KEYS:
        value = counters.get(key)
        try:
            number = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            out[key] = value
            continue
        if not math.isfinite(number) or number != 0:
            out[key] = int(number) if math.isfinite(number) and number.is_integer() else value
    return out


def export_valid(counters: Mapping[str, Any]) -> bool:
    """True when `embody export` would write this trajectory (no violations)."""
    return not violations(counters)


def sequence_verdicts(seq: Mapping[str, Any]) -> dict[str, bool | None]:
    """The verdicts of one run-manifest sequence entry (`{status, metrics: {step: {...}}}`).

    `export_valid` reads the validation counters the pipeline's `metrics` step stored; it is
    None when that step did not run for the sequence. `critic_accepted` is None without a critic,
    `physics_valid` (the `physics` step's figures) None when that step did not run or had
    nothing to replay (a robot without an `actuation` section).
    """
    ok = seq.get("status") == "ok"
    metrics = seq.get("metrics") or {}
    counters = metrics.get("metrics")
    valid: bool | None
    if not ok:
        valid = False
    elif counters is None or not all(k in counters for k in VALIDATION_KEYS):
        valid = None
    else:
        valid = export_valid(counters)
    refine = metrics.get("refine")
    accepted = None if refine is None or "accepted" not in refine else (
        ok and bool(refine["accepted"]))
    physics = metrics.get("physics")
    phys: bool | None = None if physics is None or "skipped" in physics else (ok and physics_valid(physics))
    return {"processed_ok": ok, "export_valid": valid, "critic_accepted": accepted, "physics_valid": phys}


def _flag(value: Any) -> bool | None:
    """A verdict cell as True/False/None (NumPy bools and a table's NaN blanks included)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return bool(value)


def in_default_export(row: Mapping[str, Any]) -> bool:
    """Whether `embody export` without `--include-rejected` writes this sequence: export-valid
    and not rejected by the critic (a run without a critic rejects nothing)."""
    return _flag(row.get("export_valid")) is True and _flag(row.get("critic_accepted")) is not False


def run_verdicts(per_sequence: Iterable[Mapping[str, bool | None]]) -> dict[str, int | None]:
    """Counts over a run: `total` and, per verdict, how many sequences hold it (None when no
    sequence has that verdict at all, e.g. critic_accepted of a run without a critic), plus
    `default_export` (how many `embody export` writes by default) and `rejected_export_valid`
    (export-valid sequences it leaves out because the critic rejected them)."""
    rows = list(per_sequence)
    out: dict[str, int | None] = {"total": len(rows)}
    for name in VERDICTS:
        known = [r[name] for r in rows if r.get(name) is not None]
        out[name] = sum(bool(v) for v in known) if known else None
    out["default_export"] = sum(in_default_export(r) for r in rows)
    out["rejected_export_valid"] = sum(_flag(r.get("export_valid")) is True
                                       and _flag(r.get("critic_accepted")) is False for r in rows)
    return out


def verdict_line(counts: Mapping[str, int | None]) -> str:
    """One human line: "24/24 processed ok · 19/24 export-valid · 16/24 critic-accepted ·
    24/24 physics-valid", plus what the default export leaves out of the export-valid ones and
    how to include them."""
    total = counts.get("total") or 0
    parts = []
    for name, label in (("processed_ok", "processed ok"), ("export_valid", "export-valid"),
                        ("critic_accepted", "critic-accepted"), ("physics_valid", "physics-valid")):
        value = counts.get(name)
        parts.append(f"{label} n/a" if value is None else f"{value}/{total} {label}")
    line = " · ".join(parts)
    skipped = counts.get("rejected_export_valid") or 0
    if skipped:
        line += (f" · {counts.get('default_export') or 0}/{total} in the default export: "
                 f"{skipped} export-valid {'sequence' if skipped == 1 else 'sequences'} the critic "
                 "rejected left out (`embody export --include-rejected` includes them)")
    return line


def plural(n: int, noun: str, many: str | None = None) -> str:
    """"1 artifact", "2 artifacts": counts in messages read as English."""
    return f"{n} {noun if n == 1 else (many or noun + 's')}"
