"""Body models: SMPL-X-driven skinned bodies in torch (`mannequin` default, or a user's SMPL-X)."""

from __future__ import annotations

import functools

import numpy as np
from mannequin import _io as mannequin_io

from embody.body.base import BodyModel, ConvexPiece
from embody.body.mannequin import MannequinBody
from embody.body.smplx import SMPLXBody
from embody.config.body import BodyConfig

__all__ = ["BodyModel", "ConvexPiece", "MannequinBody", "SMPLXBody", "hand_mean", "load_body_model"]


def load_body_model(cfg: BodyConfig | None = None) -> BodyModel:
    """The configured body model, built once per config (models are stateless apart from caches)."""
    return _load(cfg or BodyConfig())


@functools.lru_cache(maxsize=8)
def _load(cfg: BodyConfig) -> BodyModel:
    if cfg.backend == "smplx":
        return SMPLXBody.from_config(cfg)
    return MannequinBody()


def hand_mean() -> np.ndarray:
    """SMPL-X relaxed hand mean (30,3), left 15 then right 15: relative ↔ absolute hands."""
    return mannequin_io.load_calibration().hand_mean.astype(np.float32)
