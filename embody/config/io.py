"""`io`: overrides of what a source's files say (or its dataset's default) about frame rate,
up axis and hand convention. Unset (null) keeps the file's own; see `embody inspect`."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from embody.config.base import Section


class IOConfig(Section):
    #: Frame rate of every input sequence (`--fps`); null: from the file or its dataset default.
    fps: float | None = Field(None, gt=0.0, le=10_000.0)
    #: Up axis of the source (`--up-axis`): y, z, or camera (OpenCV, y down); null: detected.
    up_axis: Literal["y", "z", "camera"] | None = None
    #: Hand convention of the source (`--hands`): absolute (flat hand = 0) or relative (offsets
    #: from the SMPL-X hand mean); null: detected or the dataset's documented convention.
    hands: Literal["absolute", "relative"] | None = None
