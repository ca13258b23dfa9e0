"""`collision`: self-collision energy (Eq. 1) and masked test-time optimisation (Eq. 2–3)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from embody.config.base import Section

MaskPreset = Literal["hands", "hands_wrists", "arms", "upper_body", "joints"]


class CollisionConfig(Section):
    """Defaults were picked by measurement on the synthetic set (benchmarks/collision.py): the
    `arms` mask and a stronger smoothness weight than the paper's; `configs/collision/paper.yaml`
    restores the paper's setting (hands only, λ_smooth 1e-4, 500 steps)."""

    enabled: bool = True
    #: Which joints may move: a preset, or `joints` for the explicit `joints` list.
    mask: MaskPreset = "arms"
    #: Joint names (embody.motion.JOINT_NAMES) used when `mask` is `joints`.
    joints: list[str] = []
    lr: float = Field(1e-2, gt=0, le=1.0)
    steps: int = Field(500, ge=0, le=100_000)
    lambda_col: float = Field(50.0, ge=0)
    lambda_close: float = Field(1e-4, ge=0)
    lambda_smooth: float = Field(0.1, ge=0)
    #: Every n-th vertex of each part's skinned mesh (and every n-th corner of its convex
    #: pieces) is tested: a deterministic subsample, skinned only for those vertices.
    vertex_stride: int = Field(8, ge=1, le=64)
    #: Penetration (m) below which a vertex counts as touching (below the mesh resolution).
    tolerance: float = Field(1e-3, ge=0, le=0.05)
    #: Part pairs allowed to touch on purpose (e.g. [[right_hand, head]]); names as in
    #: `embody.collision.exclusions.group_names`.
    allow_pairs: list[tuple[str, str]] = []
    #: Stop once the energy is zero and the objective's relative change stays below
    #: `early_stop_rtol` for `early_stop_patience` consecutive steps.
    early_stop: bool = True
    early_stop_rtol: float = Field(1e-2, ge=0, le=1)
    early_stop_patience: int = Field(5, ge=1, le=1000)
    #: Also stop when the energy has not fallen by `early_stop_rtol` of its start value for
    #: this many steps (a residual the mask cannot resolve).
    early_stop_stall: int = Field(40, ge=1, le=100_000)
    #: The optimiser reruns the broad phase every `refresh_every` steps and keeps the
    #: candidates within `refresh_margin` (m) in between; reported energies are always exact.
    refresh_every: int = Field(5, ge=1, le=1000)
    refresh_margin: float = Field(0.02, ge=0, le=0.5)
    #: Torch intra-op threads while optimising: the many small batched ops run fastest on
    #: one thread (10x faster than two on a busy 2-core machine); parallelise over sequences.
    threads: int = Field(1, ge=1, le=256)
    #: Part volumes: convex pieces overfilling the body by more than this fraction get split.
    max_overfill: float = Field(0.10, gt=0, le=1)
