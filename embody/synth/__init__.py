"""Synthetic sign-like SMPL-X motion with recorded generator artifacts (no licensed data needed)."""

from embody.synth.dataset import default_dataset, generate_dataset
from embody.synth.generator import GENERATOR_VERSION, generate_sequence

__all__ = ["GENERATOR_VERSION", "default_dataset", "generate_dataset", "generate_sequence"]
