"""`body`: which body model backend to use."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from embody.config.base import Section


class BodyConfig(Section):
    #: `mannequin` (bundled, license-free) or `smplx` (a user's licensed SMPL-X file).
    backend: Literal["mannequin", "smplx"] = Field(
        "mannequin", description="Body model: bundled mannequin-x, or a user's SMPL-X file.")
    #: SMPLX_{NEUTRAL,MALE,FEMALE}.npz, or a folder holding them; required when backend is `smplx`.
    model_path: str | None = Field(
        None, description="SMPL-X .npz/.pkl file, or a folder with SMPLX_{GENDER}.npz.")
    #: Picks SMPLX_{GENDER}.npz when `model_path` is a folder.
    gender: Literal["neutral", "male", "female"] = Field(
        "neutral", description="Which SMPLX_{GENDER}.npz to use when model_path is a folder.")
