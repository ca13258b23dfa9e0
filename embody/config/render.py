"""`render`: settings of the render stage."""

from __future__ import annotations

from embody.config.base import Section


class RenderConfig(Section):
    pass
