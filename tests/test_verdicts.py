"""The run's verdict line and `embody export`'s default say the same thing: the line counts what
the default export writes, and names the export-valid sequences it leaves out and the flag that
includes them (issue 36: "4/4 export-valid" while the export wrote 0 files)."""

from __future__ import annotations

import math

import pandas as pd

from embody.verdicts import in_default_export, run_verdicts, verdict_line


def _row(valid, accepted):
    return {"processed_ok": valid is not False, "export_valid": valid, "critic_accepted": accepted}


def test_the_verdict_line_says_what_the_default_export_writes() -> None:
    rows = [_row(True, False)] * 4  # the H1 run: every sequence export-valid, every one rejected
    counts = run_verdicts(rows)
    assert counts["export_valid"] == 4 and counts["default_export"] == 0
    assert counts["rejected_export_valid"] == 4
    line = verdict_line(counts)
    assert "4/4 export-valid" in line and "0/4 in the default export" in line
    assert "4 export-valid sequences the critic rejected left out" in line
    assert "--include-rejected" in line

    mixed = [_row(True, True), _row(True, False), _row(False, False), _row(True, None)]
    counts = run_verdicts(mixed)
    assert counts["default_export"] == 2 and counts["rejected_export_valid"] == 1
    assert "2/4 in the default export: 1 export-valid sequence the critic rejected" in verdict_line(counts)
    assert [in_default_export(r) for r in mixed] == [True, False, False, True]


def test_without_rejections_the_line_is_the_four_verdicts() -> None:
    counts = run_verdicts([_row(True, None), _row(False, None)])
    assert counts["default_export"] == 1 and counts["rejected_export_valid"] == 0
    assert verdict_line(counts) == ("1/2 processed ok · 1/2 export-valid · critic-accepted n/a · "
                                    "physics-valid n/a")


def test_table_cells_count_like_flags() -> None:
    """The report counts from a table (NumPy bools, NaN blanks): the same numbers."""
    frame = pd.DataFrame([_row(True, False), _row(True, True), _row(True, None)])
    records = frame.astype(object).where(frame.notna(), math.nan).to_dict("records")
    assert run_verdicts(records)["default_export"] == run_verdicts(
        [_row(True, False), _row(True, True), _row(True, None)])["default_export"] == 2
