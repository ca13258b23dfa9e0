"""`critic`: settings of the critic stage."""

from __future__ import annotations

from embody.config.base import Section


class CriticConfig(Section):
    pass
