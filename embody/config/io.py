"""`io`: bounds on what an input file may hold, checked on load (hostile or broken files)."""

from __future__ import annotations

import math

from pydantic import Field, model_validator

from embody.config.base import Section


class IOConfig(Section):
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
