"""`ik`: settings of the ik stage."""

from __future__ import annotations

from embody.config.base import Section


class IKConfig(Section):
    pass
