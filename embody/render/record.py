"""The render stage of the pipeline: one sequence's comparison sheet (and preview) as an artifact.

The critic only renders when it looks at images; this stage renders every sequence's final
trajectory so each run keeps a picture a person can check, and the report shows stored sheets
instead of re-rendering them.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from embody.config.render import RenderConfig
from embody.render.compare import open_renderer, render_comparison, stream_preview


@dataclass
class SequenceRender:
    """Keyframes, the reference-over-robot sheet PNG and the optional animated preview bytes."""

    keyframes: np.ndarray
    sheet_png: bytes
    preview: bytes | None = None
    preview_suffix: str | None = None

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {"keyframes": np.asarray(self.keyframes, dtype=np.int64),
                  "sheet_png": np.frombuffer(self.sheet_png, dtype=np.uint8)}
        if self.preview is not None:
            arrays["preview"] = np.frombuffer(self.preview, dtype=np.uint8)
        return arrays

    def to_attrs(self) -> dict[str, Any]:
        return {"preview_suffix": self.preview_suffix}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "SequenceRender":
        preview = arrays.get("preview")
        return cls(np.asarray(arrays["keyframes"]), np.asarray(arrays["sheet_png"]).tobytes(),
                   None if preview is None else np.asarray(preview).tobytes(),
                   attrs.get("preview_suffix"))


def render_sequence(motion, body, fit, robot, q: np.ndarray, keyframes: np.ndarray,
                    cfg: RenderConfig, title: str = "") -> SequenceRender:
    """Render the final trajectory `q` beside the reference body at `keyframes` (pick them with
    `select_keyframes` on the reference wrists, as the critic loop does, or take the loop's).

    The preview's frames (`render.preview_fps`, first view; only the part of the image the
    bodies reach with `render.preview_crop`) and the keyframes (whole) are drawn in one pass;
    the sheet's first view takes its keyframes from it, so only the other views are drawn for
    the sheet."""
    keys = np.asarray(keyframes)
    q = np.asarray(q)
    renderer = open_renderer(robot, body, fit, cfg)
    try:
        preview = suffix = None
        with tempfile.TemporaryDirectory(prefix="embody-preview-") as tmp:
            path, drawn = stream_preview(renderer, cfg, motion, q, Path(tmp) / "preview", keys)
            if path is not None:
                preview, suffix = path.read_bytes(), path.suffix
        comp = render_comparison(renderer, cfg, keys, motion.fps, q, drawn=drawn, motion=motion)
        sheet = comp.sheet_png(title)
    finally:
        renderer.close()
    return SequenceRender(keys, sheet, preview, suffix)
