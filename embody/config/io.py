"""`io`: how input files are read and what they may hold.

Overrides of what a source's files say (or its dataset's default) about frame rate, up axis and
hand convention (unset keeps the file's own; see `embody inspect`), and bounds checked on load
against hostile or broken files.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from embody.config.base import Section


class IOConfig(Section):
    #: Frame rate of every input sequence (`--fps`); null: from the file or its dataset default.
    fps: float | None = Field(None, gt=0.0, le=10_000.0)
    #: Up axis of the source (`--up-axis`): y, z, or camera (OpenCV, y down); null: detected.
    up_axis: Literal["y", "z", "camera"] | None = None
    #: Hand convention of the source (`--hands`): absolute (flat hand = 0) or relative (offsets
    #: from the SMPL-X hand mean); null: detected or the dataset's documented convention.
    hands: Literal["absolute", "relative"] | None = None
    #: Longest sequence accepted (frames); npz/npy are checked from their headers, before any
    #: decompression, SOKE folders by counting frame files.
    max_frames: int = Field(50_000, ge=2, le=10_000_000)
    #: Accepted frame-rate range (Hz): outside it velocities and resampling are meaningless.
    min_fps: float = Field(1.0, gt=0)
    max_fps: float = Field(1000.0, gt=0, le=1e6)
    #: Largest accepted |axis-angle| of any joint (rad); real poses stay within 2π.
    max_axis_angle: float = Field(10 * math.pi, gt=0)
    #: Largest accepted |translation| component (m).
    max_translation: float = Field(1000.0, gt=0)
    #: Let SOKE split names and CSV manifest paths point outside the dataset's folder.
    allow_outside_paths: bool = False

    @model_validator(mode="after")
    def _fps_range(self) -> "IOConfig":
        if self.min_fps > self.max_fps:
            raise ValueError(f"min_fps {self.min_fps} > max_fps {self.max_fps}")
        return self
