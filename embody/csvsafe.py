"""CSV cells that a spreadsheet will not run as formulas.

Sequence texts and error messages come from input files; a cell starting with `=`, `+`, `-`,
`@` (or a tab/CR) is a formula to Excel and LibreOffice ("CSV injection"). Such text cells get
a leading `'`, which spreadsheets show as a literal; numbers are left alone.
"""

from __future__ import annotations

from typing import Any

import pandas as pd

FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def safe_cell(value: Any) -> Any:
    if isinstance(value, str) and value.startswith(FORMULA_STARTS):
        return "'" + value
    return value


def csv_safe(frame: pd.DataFrame) -> pd.DataFrame:
    """A copy of `frame` with every formula-like text cell escaped (column names included)."""
    out = frame.copy()
    for col in out.columns:
        if not pd.api.types.is_numeric_dtype(out[col]):  # object or pandas' str dtype
            out[col] = out[col].map(safe_cell)
    out.columns = [safe_cell(c) for c in out.columns]
    return out
