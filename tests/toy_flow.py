"""Stand-ins for the orchestration tests: a step result (one array `x` and its metrics, stored
and loaded the way the real results are: `to_arrays`, `to_attrs`, `from_arrays`) and a folder of
small AMASS sequences."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Toy:
    x: np.ndarray
    metrics: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x)
        self.metrics = dict(self.metrics or {})

    def to_arrays(self):
        return {"x": self.x}

    def to_attrs(self):
        return {"metrics": self.metrics}

    @classmethod
    def from_arrays(cls, arrays, attrs):
        return cls(np.asarray(arrays["x"]), dict(attrs.get("metrics") or {}))


def write_amass(folder: Path, n: int, frames: int = 6,
                frames_of: dict[int, int] | None = None) -> Path:
    """`n` AMASS npz files `seq000.npz`, … of `frames` random poses (`frames_of[i]` for
    sequence i where given), seeded."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        t = (frames_of or {}).get(i, frames)
        np.savez(folder / f"seq{i:03d}.npz",
                 poses=rng.normal(0, 0.1, (t, 165)).astype(np.float32),
                 trans=np.zeros((t, 3), np.float32), betas=np.zeros(10, np.float32),
                 gender="neutral", mocap_frame_rate=30.0)
    return folder
