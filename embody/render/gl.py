"""Offscreen OpenGL contexts for MuJoCo without a display.

`MUJOCO_GL` is read when mujoco is first imported, and another stage may import mujoco before
us; so the backend class is imported explicitly (egl, falling back to osmesa) instead of relying
on the variable. We still set `MUJOCO_GL=egl` when unset, for code that uses `mujoco.Renderer`.
"""

from __future__ import annotations

import logging
import os

from embody.errors import EmbodyError

os.environ.setdefault("MUJOCO_GL", "egl")

log = logging.getLogger(__name__)


class RenderError(EmbodyError):
    """No offscreen OpenGL context could be created (no EGL and no OSMesa)."""


def create_context(width: int, height: int, backend: str = "egl"):
    """A current offscreen GL context of `backend`, else the other one; caller must `.free()` it."""
    order = [backend] + [b for b in ("egl", "osmesa") if b != backend]
    errors = []
    for name in order:
        try:
            if name == "egl":
                from mujoco.egl import GLContext
            else:
                from mujoco.osmesa import GLContext
            ctx = GLContext(width, height)
            ctx.make_current()
            if name != backend:
                log.warning("OpenGL backend %s unavailable, using %s", backend, name)
            return ctx
        except Exception as exc:  # noqa: BLE001 - any failure means "try the next backend"
            errors.append(f"{name}: {type(exc).__name__}: {exc}")
    raise RenderError("no offscreen OpenGL backend works (" + "; ".join(errors) + ")")
