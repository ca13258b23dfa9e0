"""The run summary's three verdicts per sequence and per run (see `embody.verdicts`)."""

from __future__ import annotations

from typing import Any

from embody.verdicts import run_verdicts, sequence_verdicts

__all__ = ["layout_warnings", "verdict_summary"]


def verdict_summary(manifest: Any) -> dict[str, Any]:
    """{"verdicts": counts over the run, "sequences": {id: the three verdicts}, and
    "layout_warnings" when a source's keys and data disagree (see `layout_warnings`)}."""
    per = {sid: sequence_verdicts(seq) for sid, seq in sorted(manifest.sequences.items())}
    out: dict[str, Any] = {"verdicts": run_verdicts(per.values()), "sequences": per}
    warnings = layout_warnings(manifest)
    if warnings:
        out["layout_warnings"] = warnings
    return out


def layout_warnings(manifest: Any) -> list[dict[str, Any]]:
    """Each distinct layout warning of the run's sources once (`embody.io.conventions.
    layout_check`), with how many sequences and which ones it concerns."""
    seen: dict[str, list[str]] = {}
    for sid, seq in sorted(manifest.sequences.items()):
        text = (seq.get("metrics") or {}).get("source", {}).get("layout_warnings")
        for warning in str(text).split(" | ") if text else ():
            seen.setdefault(warning, []).append(sid)
    return [{"warning": w, "count": len(ids), "ids": ids} for w, ids in seen.items()]
