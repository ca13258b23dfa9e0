"""`collision`: self-collision energy (Eq. 1) and masked test-time optimisation (Eq. 2–3)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from embody.config.base import Section, check_window
from embody.device import DeviceSpec

MaskPreset = Literal["hands", "hands_wrists", "arms", "upper_body", "joints"]


class CollisionConfig(Section):
    """Defaults were picked by measurement on the synthetic set (benchmarks/collision.py
    --sweep, 24 sequences, 24 colliding): the `arms` mask, a stronger smoothness weight than the
    paper's, and a strong closeness pull with a 2 mm clearance target, which cut the median
    Pose MSE 8x while the targets (100% improved, median reduction ≥ 90%, ΔAccel median
    ≤ +5.71e-3) hold with margin. `configs/collision/paper.yaml` restores the paper's setting.

    ======== ========= ====== ========== ======== =========== =========
    λ_close  clearance stall  red. med.  red. min Pose MSE    ΔAccel
                              (%)        (%)      (median)    (median)
    ======== ========= ====== ========== ======== =========== =========
    1e-4     0         40     100.00     98.8     0.163       −6.9e-3
    1e-2     0         40     100.00     98.8     0.118       −5.0e-3
    0.1      0         40     100.00     98.8     0.084       −1.4e-3
    1        0         40     99.98      98.5     0.043       +9.5e-4
    3        0         40     99.87      97.1     0.033       +2.3e-3
    3        2 mm      40     99.95      97.6     0.036       +2.7e-3
    10       0         40     99.25      93.4     0.018       +3.3e-3
    10       2 mm      40     99.44      97.2     0.021       +2.8e-3
    10       5 mm      40     99.85      98.0     0.024       +2.6e-3
    **10**   **2 mm**  **20** **99.28**  **94.2** **0.021**   **+2.8e-3**
    30       2 mm      40     97.71      87.0     0.012       +4.2e-3
    ======== ========= ====== ========== ======== =========== =========

    Since issue 13 the optimiser is judged by the mesh penetration depth (`collision.depth`)
    and runs as a constraint: per-frame λ continuation, no stop while a frame penetrates, and
    only the frames within `blend_s` of a penetration move (the table above predates that).

    Since 2026-11-26 (s4-colquality, `benchmarks/collision.py --n 24`) the Adam step shares its
    second moment per frame (`adam_norm: frame`, lr 3e-3: the step follows the gradient's
    direction, which moves the joints with the longest lever arm rather than every masked joint
    alike), decays once every frame is clear (`lr_decay` 0.8, so the closeness pull settles
    instead of a few frames flickering in and out of contact until `steps` run out) and λ grows
    more gently (1.2: less overshoot past the contact). The optimiser alone (no polish) went
    from Pose MSE median 0.0224 to 0.0209 and 6011 to 5304 steps over the 24 sequences; with
    the depth polish Table I's median is 0.0218 (issue 13's 0.0206 not reached). lr 2e-3 or
    5e-3, λ growth 1.5, a 1 mm clearance or a 2–4 mm residual depth allowance did not do
    better (docs/performance.md, 2026-11-26).

    Since 2026-11-26 (s6-adam) a last `pull_back` shrinks each frame's correction towards the
    input to the smallest fraction the mesh judge still finds within `pull_back_depth` (1 mm,
    the `tolerance`): the clearance and Adam's overshoot are measured on the convex pieces,
    which overfill the skin, so the mesh stays clear down to s ≈ 0.97–0.98 (Table I Pose MSE
    median 0.0218 → see docs/performance.md, 2026-11-26 (s6-adam)).

    With per-parameter Adam (the paper preset's), each parameter's step is normalised alone,
    so with a weak closeness term joints barely touched by a collision still drift by ~lr per
    step; a strong pull returns them once the collision
    is resolved (the best zero-energy pose is kept), and the clearance keeps that pull from
    settling at residual depth. The pull-back needs ~20 steps after the last energy gain, so
    the stall window was 20 (40 gave the same result 1.7x slower; 1 since s9-adamfast, see
    `early_stop_stall`). λ_close = 30 halves the
    Pose MSE again but brings ΔAccel near its limit and the worst reduction to 87%.
    """

    enabled: bool = True
    #: Which joints may move: a preset, or `joints` for the explicit `joints` list.
    mask: MaskPreset = "arms"
    #: Joint names (embody.motion.JOINT_NAMES) used when `mask` is `joints`.
    joints: list[str] = []
    #: `adam`: the first-order path (`lr`, `steps`), the measured default. `gauss_newton`:
    #: Levenberg-Marquardt with analytic Jacobians and a banded solve
    #: (`embody.collision.solve`); frames it leaves penetrating go on to Adam from its pose.
    #: Opt-in: it meets the depth targets on the 24 default sequences with less CPU (seqs 0-3:
    #: optimiser 7.1 → 2.0 s per 150 frames, whole call with the mesh judge 12.6 → 10.3), but
    #: its Pose MSE median is 0.0225 (Adam 0.0218; docs/performance.md, s6-gn).
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
    #: candidate rows of 2 cm at the same iterations and metrics (seqs 0-3).
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
    #: it still penetrates, up to `lambda_max`. 1.3 since s10-adam (was 1.2): a frame whose
    #: correction is large clears only once λ_col·depth outweighs λ_close·‖δ‖ (λ_col ~ 5e3
    #: from 50, i.e. ~25 refreshes at 1.2), so that tail set the step count; 1.3 cut Adam's
    #: steps 25 % on seqs 0, 3, 12, 14, 15 at the same Pose MSE (1.4-1.5 or a higher starting
    #: λ_col: fewer steps, worse Pose MSE; docs/performance.md 2026-11-27 (s10-adam)).
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
    #: The window was 0.25 s until s14-pull: on the 24 default sequences 0.25 / 0.15 / 0.1 s
    #: gave Pose MSE median 0.02054 / 0.02020 / 0.02004, ΔAccel median 6.96e-5 / 6.10e-5 /
    #: 5.36e-5 and max 6.50e-3 / 5.40e-3 / 4.99e-3 (a wide envelope holds s up around each
    #: frame's need, which costs both; docs/performance.md, s14-pull).
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
    #: meanwhile). Never stops while a frame penetrates: then `steps` bound the run. Since
    #: s9-adamfast 1 (the next refresh, 5 steps later; was 20): the mesh-judged `pull_back`
    #: now does the closeness job (it shrinks each frame's correction to the smallest still
    #: clear fraction), so the settling steps bought nothing measurable (24 sequences: Pose MSE
    #: median 0.0199 either way, docs/performance.md 2026-11-26 (s9-adamfast)) for ~15 Adam
    #: steps a sequence.
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
    #: (benchmarks/memory.py: ~3.9 GB peak with 1,000-frame windows; sign clips average ~160).
    window_frames: int = Field(500, ge=16, le=1_000_000)
    window_overlap: int = Field(30, ge=2, le=10_000)

    @model_validator(mode="after")
    def _overlap_fits(self) -> "CollisionConfig":
        check_window(self.window_frames, self.window_overlap)
        return self
