"""`body`: which body model backend to use."""

from __future__ import annotations

from typing import Literal

from embody.config.base import Section


class BodyConfig(Section):
    backend: Literal["mannequin", "smplx"] = "mannequin"
    #: Path to a user's SMPLX_{NEUTRAL,MALE,FEMALE}.npz; required when backend is `smplx`.
    model_path: str | None = None
    gender: Literal["neutral", "male", "female"] = "neutral"
