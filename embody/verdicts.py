"""The three verdicts on a sequence: processed ok, export-valid, critic-accepted.

"Success" means three different things, so every place that counts it (the run's closing
summary, `summary.json`, the report's first table and `embody export`) asks this module, and
they cannot disagree. NumPy-free and torch-free on purpose: the run's closing summary uses it.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

__all__ = ["VALIDATION_KEYS", "VERDICTS", "export_valid", "plural", "run_verdicts",
           "sequence_verdicts", "verdict_line", "violations"]

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
}


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
    None when that step did not run for the sequence. `critic_accepted` is None without a critic.
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
    return {"processed_ok": ok, "export_valid": valid, "critic_accepted": accepted}


def run_verdicts(per_sequence: Iterable[Mapping[str, bool | None]]) -> dict[str, int | None]:
    """Counts over a run: `total` and, per verdict, how many sequences hold it (None when no
    sequence has that verdict at all, e.g. critic_accepted of a run without a critic)."""
    rows = list(per_sequence)
    out: dict[str, int | None] = {"total": len(rows)}
    for name in VERDICTS:
        known = [r[name] for r in rows if r.get(name) is not None]
        out[name] = sum(bool(v) for v in known) if known else None
    return out


def verdict_line(counts: Mapping[str, int | None]) -> str:
    """One human line: "24/24 processed ok · 19/24 export-valid · 16/24 critic-accepted"."""
    total = counts.get("total") or 0
    parts = []
    for name, label in (("processed_ok", "processed ok"), ("export_valid", "export-valid"),
                        ("critic_accepted", "critic-accepted")):
        value = counts.get(name)
        parts.append(f"{label} n/a" if value is None else f"{value}/{total} {label}")
    return " · ".join(parts)


def plural(n: int, noun: str, many: str | None = None) -> str:
    """"1 artifact", "2 artifacts": counts in messages read as English."""
    return f"{n} {noun if n == 1 else (many or noun + 's')}"
