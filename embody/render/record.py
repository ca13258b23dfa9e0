"""The render stage of the pipeline: one sequence's comparison sheet (and preview) as an artifact.

The critic only renders when it looks at images; this stage renders every sequence's final
trajectory so each run keeps a picture a person can check, and the report shows stored sheets
instead of re-rendering them.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from embody.config.render import RenderConfig
from embody.render.compare import open_renderer, render_comparison, stream_preview

__all__ = ["SequenceRender", "kept_renderer", "render_sequence"]


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
    slot = getattr(_KEPT, "slot", None)
    key = _renderer_key(robot, body, fit, cfg) if slot is not None else None
    renderer = _take(slot, key, robot, body) if slot is not None else None
    if renderer is None:
        renderer = open_renderer(robot, body, fit, cfg)
    done = False
    try:
        preview = suffix = None
        with tempfile.TemporaryDirectory(prefix="embody-preview-") as tmp:
            path, drawn = stream_preview(renderer, cfg, motion, q, Path(tmp) / "preview", keys)
            if path is not None:
                preview, suffix = path.read_bytes(), path.suffix
        comp = render_comparison(renderer, cfg, keys, motion.fps, q, drawn=drawn, motion=motion)
        sheet = comp.sheet_png(title)
        done = True
    finally:
        if done and slot is not None:  # kept for this thread's next sequence
            slot.update(key=key, robot=robot, body=body, renderer=renderer)
        else:  # a renderer that failed mid-sequence is not reused
            renderer.close()
    return SequenceRender(keys, sheet, preview, suffix)


#: This thread's kept renderer, inside `kept_renderer` (`slot`: key, robot, body, renderer).
_KEPT = threading.local()


@contextmanager
def kept_renderer() -> Iterator[None]:
    """Inside the block, this thread's `render_sequence` calls share one open renderer while
    the robot, body, shape fit and render config stay the same (a run's sequences), instead of
    opening one per sequence: the scene, its GL context and the reference skin are built once
    (~0.13 CPU-s of the ~0.8 a sequence's render took, 2026-11-27). Each image sets the whole
    state it draws (the robot's pose, the skin's bone poses, the camera), so the pictures are
    the same bytes as with a fresh renderer. A GL context is current in one thread only, hence
    per thread; the renderer is closed when another is needed and at the block's end (worker
    processes keep one for their lifetime, `tasks.workers`)."""
    outer = getattr(_KEPT, "slot", None)
    slot: dict[str, Any] = {}
    _KEPT.slot = slot
    try:
        yield
    finally:
        _KEPT.slot = outer
        renderer = slot.pop("renderer", None)
        if renderer is not None:
            renderer.close()


def _renderer_key(robot: Any, body: Any, fit: Any, cfg: RenderConfig) -> tuple[int, int, bytes]:
    """What an open renderer was built from: the robot and body (by identity; the slot holds
    them, so their ids are not reused) and the fit and render config (by content)."""
    h = hashlib.blake2b(digest_size=16)
    for name, a in sorted(fit.to_arrays().items()):
        a = np.ascontiguousarray(a)
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    h.update(json.dumps(fit.to_attrs(), sort_keys=True, default=str).encode())
    h.update(cfg.model_dump_json().encode())
    return id(robot), id(body), h.digest()


def _take(slot: dict[str, Any], key: tuple, robot: Any, body: Any) -> Any:
    """The kept renderer when it was built from the same inputs (taken out of the slot while
    it draws), else None (a kept one for other inputs is closed)."""
    renderer = slot.pop("renderer", None)
    if renderer is None:
        return None
    if slot.get("key") == key and slot.get("robot") is robot and slot.get("body") is body:
        return renderer
    renderer.close()
    return None
