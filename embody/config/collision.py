"""`collision`: settings of the collision stage."""

from __future__ import annotations

from embody.config.base import Section


class CollisionConfig(Section):
    pass
