"""Base class of config sections and the canonical JSON that content keys hash."""

from __future__ import annotations

import json
import math
from typing import Any

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    """A config section: typed, unknown keys rejected, immutable once loaded."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


def _normalise(value: Any) -> Any:
    if isinstance(value, float):
        if not math.isfinite(value):
            return repr(value)
        # 12 significant digits: stable across platforms, insensitive to float noise.
        normalised = float(f"{value:.12g}")
        return int(normalised) if normalised.is_integer() else normalised
    if isinstance(value, dict):
        return {str(k): _normalise(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_normalise(v) for v in value]
    return value


def canonical_json(value: BaseModel | dict[str, Any] | list[Any]) -> str:
    """Sorted keys, no whitespace, normalised floats: the text a content key hashes."""
    data = value.model_dump(mode="json") if isinstance(value, BaseModel) else value
    return json.dumps(_normalise(data), sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def check_window(frames: int, overlap: int) -> None:
    """Windowed processing (collision, IK): a cross-fade may cover at most half a window."""
    if overlap * 2 > frames:
        raise ValueError("window_overlap must be at most half of window_frames")
