"""`collision`: self-collision energy (Eq. 1) and masked test-time optimisation (Eq. 2–3)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from embody.config.base import Section, check_window
from embody.device import DeviceSpec

MaskPreset = Literal["hands", "hands_wrists", "arms", "upper_body", "joints"]


class CollisionConfig(Section):
    """Collision mitigation: masked Adam on the volumetric energy L_col, then a depth-guided
    polish and a mesh-judged pull-back towards the input.

    The defaults were chosen by measurement on the 24-sequence synthetic set
    (`benchmarks/collision.py`): the `arms` mask, a stronger smoothness weight than the paper's,
    a strong closeness pull with a 2 mm clearance target, per-frame λ continuation, and no stop
    while a frame penetrates; only frames within `blend_s` of a penetration move.
    `configs/collision/paper.yaml` restores the paper's setting (Eq. 2-3).
    """

    enabled: bool = True
    #: Which joints may move: a preset, or `joints` for the explicit `joints` list.
    mask: MaskPreset = "arms"
    #: Joint names (embody.motion.JOINT_NAMES) used when `mask` is `joints`.
    joints: list[str] = []
    #: `adam`: the first-order path (`lr`, `steps`), the measured default. `gauss_newton`:
    #: Levenberg-Marquardt with analytic Jacobians and a banded solve
    #: (`embody.collision.solve`); frames it leaves penetrating go on to Adam from its pose.
    #: Opt-in: it meets the depth targets for less CPU, at a higher Pose MSE than Adam.
    solver: Literal["gauss_newton", "adam"] = "adam"
    #: LM iterations (each one banded solve + re-evaluation of the near points).
    solver_iterations: int = Field(40, ge=1, le=10_000)
    #: The LM path's starting λ_col (Adam's is `lambda_col`): high enough that the first
    #: steps already remove most of the depth, since λ only grows once a step has settled.
    solver_lambda_col: float = Field(300.0, ge=0)
    #: λ continuation factor, applied to the frames still penetrating once the LM step at the
    #: current λ has settled (`solver_rtol`).
    solver_lambda_growth: float = Field(4.0, ge=1, le=1000)
    #: Accepted LM steps between broad-phase refreshes of the near (point, piece) pairs.
    solver_refresh_every: int = Field(3, ge=1, le=1000)
    #: The LM path's broad-phase margin (m; Adam's is `refresh_margin`): 1 cm keeps half the
    #: candidate rows of 2 cm at the same iterations and metrics.
    solver_refresh_margin: float = Field(0.01, ge=0, le=0.5)
    #: Damping trials (solves) per LM iteration before it gives up on a step.
    solver_trials: int = Field(8, ge=1, le=100)
    #: An LM step that lowers the objective by less than this has settled: λ grows on the
    #: frames still penetrating, or, once every frame is clear, the solve stops.
    solver_rtol: float = Field(1e-2, ge=0, le=1)
    #: Adam's second moment per `parameter` (torch's Adam, the paper's) or shared per `frame`
    #: (the step keeps the gradient's direction within a frame; `optimize._FrameAdam`).
    adam_norm: Literal["parameter", "frame"] = "frame"
    lr: float = Field(3e-3, gt=0, le=1.0)
    steps: int = Field(500, ge=0, le=100_000)
    #: Once a refresh first finds every frame clear, the step size shrinks by `lr_decay` at
    #: each refresh down to `lr_floor`·lr: Adam's ~lr steps (≈5 mm at the hand) exceed the
    #: clearance, so at a constant lr a few frames flicker in and out of contact for hundreds
    #: of steps while the closeness term drifts up.
    lr_decay: float = Field(0.8, gt=0, le=1)
    lr_floor: float = Field(0.05, gt=0, le=1)
    lambda_col: float = Field(50.0, ge=0)
    lambda_close: float = Field(10.0, ge=0)
    lambda_smooth: float = Field(0.1, ge=0)
    #: Every n-th vertex of each part's skinned mesh (and every n-th corner of its convex
    #: pieces) is tested for the reported (paper) energies: a deterministic subsample.
    vertex_stride: int = Field(8, ge=1, le=64)
    #: The same for the optimiser and its stopping test; the broad phase skips points far
    #: from contact, so every vertex near one is evaluated.
    contact_stride: int = Field(8, ge=1, le=64)
    #: Frames farther than this (s) from any penetrating frame are left unchanged; the
    #: correction fades in and out over it (cosine).
    blend_s: float = Field(0.5, ge=0, le=10)
    #: λ continuation: a frame's λ_col is multiplied by this at each broad-phase refresh while
    #: it still penetrates, up to `lambda_max`. A frame with a large correction clears only once
    #: λ_col·depth outweighs λ_close·‖δ‖, so this factor sets the step count; faster growth
    #: costs Pose MSE.
    lambda_growth: float = Field(1.3, ge=1, le=100)
    lambda_max: float = Field(1e5, gt=0)
    #: Weight of the limb core-capsule term (`embody.collision.capsules`) that separates arms
    #: passed through each other (the point energy alone cancels there); 0 turns it off.
    capsule_weight: float = Field(10.0, ge=0)
    #: Measure the mesh penetration depth before/after (`embody.collision.depth`) into the
    #: metrics (frames over 2 / 5 mm, max and median depth).
    depth_metrics: bool = True
    #: Depth-guided polish (m; 0 off): frames the mesh-depth judge still finds deeper than this
    #: after the optimiser are optimised once more, against every vertex (stride 1, the
    #: subsample can straddle a thin finger) within `blend_s` of them; the judge only picks
    #: the frames, the energy minimised stays L_col. Needs `depth_metrics`.
    depth_polish: float = Field(0.002, ge=0, le=0.05)
    #: Pull-back (`optimize.pull_back`, needs `depth_metrics`): after the optimiser and the
    #: polish, each frame's correction is shrunk towards the input to the smallest fraction
    #: at which the mesh judge finds it no deeper than `pull_back_depth` (m; or than before,
    #: if deeper), found by at most `pull_back_iterations` regula-falsi steps (each judging
    #: only the frames not yet settled) and smoothed in time over `pull_back_window_s` (s).
    #: A wider window holds s up around each frame's need, which costs Pose MSE and ΔAccel.
    pull_back: bool = True
    pull_back_depth: float = Field(0.001, ge=0, le=0.05)
    pull_back_iterations: int = Field(5, ge=1, le=50)
    pull_back_window_s: float = Field(0.1, ge=0, le=10)
    #: Penetration (m) below which a vertex counts as touching (below the mesh resolution).
    tolerance: float = Field(1e-3, ge=0, le=0.05)
    #: The optimiser pushes points this far (m) beyond the tolerance, so the closeness pull
    #: settles with the surfaces apart rather than at residual depth; reported energies use
    #: `tolerance` alone.
    clearance: float = Field(0.002, ge=0, le=0.01)
    #: Part pairs allowed to touch on purpose (e.g. [[right_hand, head]]); names as in
    #: `embody.collision.exclusions.group_names`.
    allow_pairs: list[tuple[str, str]] = []
    #: Stop `early_stop_stall` steps after every frame is clear (the closeness pull settles
    #: meanwhile). Never stops while a frame penetrates: then `steps` bound the run. One
    #: refresh is enough: the mesh-judged `pull_back` does the closeness job afterwards.
    early_stop: bool = True
    early_stop_rtol: float = Field(1e-2, ge=0, le=1)
    early_stop_patience: int = Field(5, ge=1, le=1000)
    early_stop_stall: int = Field(1, ge=1, le=100_000)
    #: The optimiser reruns the broad phase every `refresh_every` steps and keeps the
    #: candidates within `refresh_margin` (m) in between; reported energies are always exact.
    refresh_every: int = Field(5, ge=1, le=1000)
    refresh_margin: float = Field(0.02, ge=0, le=0.5)
    #: Torch intra-op threads while optimising: the many small batched ops run fastest on
    #: one thread (10x faster than two on a busy 2-core machine); parallelise over sequences.
    threads: int = Field(1, ge=1, le=256)
    #: Where the optimiser's torch work runs (`embody.device`): `cpu` (the default: the same
    #: content hashes on every machine), `cuda`, or `auto` (CUDA when present). The mesh
    #: judge and the Gauss-Newton path's banded solve stay on the CPU.
    device: DeviceSpec = "cpu"
    #: Part volumes: convex pieces overfilling the body by more than this fraction get split.
    max_overfill: float = Field(0.10, gt=0, le=1)
    #: Longer sequences are mitigated in windows of this many frames sharing `window_overlap`
    #: frames (cross-faded), so memory is bounded by the window, not the sequence length
    #: (`benchmarks/memory.py`; sign clips average ~160 frames).
    window_frames: int = Field(500, ge=16, le=1_000_000)
    window_overlap: int = Field(30, ge=2, le=10_000)

    @model_validator(mode="after")
    def _overlap_fits(self) -> "CollisionConfig":
        check_window(self.window_frames, self.window_overlap)
        return self
