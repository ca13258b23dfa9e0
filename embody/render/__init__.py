"""Offscreen MuJoCo rendering: reference body and robot from the same cameras, keyframes,
comparison sheets and animated previews."""

from embody.render.gl import RenderError, create_context
from embody.render.keyframes import select_keyframes
from embody.render.preview import write_preview
from embody.render.scene import SceneRenderer
from embody.render.sheet import comparison_sheet, png_bytes

__all__ = ["RenderError", "SceneRenderer", "comparison_sheet", "create_context", "png_bytes",
           "select_keyframes", "write_preview"]
