"""The run summary's three verdicts per sequence and per run (see `embody.verdicts`)."""

from __future__ import annotations

from typing import Any

from embody.verdicts import run_verdicts, sequence_verdicts

__all__ = ["verdict_summary"]


def verdict_summary(manifest: Any) -> dict[str, Any]:
    """{"verdicts": counts over the run, "sequences": {id: the three verdicts}}."""
    per = {sid: sequence_verdicts(seq) for sid, seq in sorted(manifest.sequences.items())}
    return {"verdicts": run_verdicts(per.values()), "sequences": per}
