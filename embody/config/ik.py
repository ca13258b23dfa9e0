"""`ik`: shape fit, whole-sequence IK, hands and control-rate resampling."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from embody.config.base import Section, check_window


class IKConfig(Section):
    # --- shape fit (Eq. 4) ---
    shape_iterations: int = Field(300, ge=1, le=100_000)
    shape_lr: float = Field(0.05, gt=0, le=10)
    #: λ_β of ‖β‖²: keeps the body plausible while it stretches towards the robot.
    shape_beta_reg: float = Field(1e-3, ge=0)
    #: Also fit one global scale (robots are ~0.7× a human: betas alone cannot get there).
    shape_fit_scale: bool = True
    # --- IK costs (targets in metres / radians, torso frame) ---
    #: Wrist position. 1 lets the location-preserving terms (hand points, hand clearance) and the
    #: regularisers shape where the hand goes relative to the robot's own face and body; plain
    #: tracking of the human's wrists wants it 80× heavier (`configs/ik/tracking.yaml`), which
    #: costs sign-fidelity location error here.
    w_wrist_pos: float = Field(1.0, ge=0)
    #: Wrist orientation error (rad², rotation vector) against position (m²).
    w_wrist_rot: float = Field(0.02, ge=0)
    w_elbow_pos: float = Field(0.01, ge=0)
    #: Torso orientation (spine3 → torso link): a leaning signer gives a leaning robot within its
    #: waist limits, so chest-anchored targets (below) stay where the chest is.
    w_torso_rot: float = Field(0.01, ge=0)
    w_head_rot: float = Field(0.0, ge=0)
    #: Second differences of q (rad²): smoothness over the whole sequence. Redundant motion
    #: (elbow swivel, waist) is smoothed for free; tracking barely pays at this weight.
    w_smooth: float = Field(0.02, ge=0)
    #: Third differences of q (rad², jerk, what the jerk metric measures): frequency-aware
    #: smoothness, penalising slow signing motion less than Δ² does for the same jerk. Off by
    #: default: it halves the jerk but loses accuracy on frames that are easy to reach.
    w_jerk: float = Field(0.0, ge=0)
    #: Pull of the arm joints towards the robot's `rest` pose: resolves redundancy gently.
    w_posture: float = Field(1e-5, ge=0)
    #: Pull of the waist joints towards rest: the torso stays upright unless the arms need it.
    w_waist_posture: float = Field(1e-3, ge=0)
    #: Hinge on joint speeds past their limits (rad² per step): tracking stays within the limits
    #: instead of lagging behind a clamp applied afterwards.
    w_velocity: float = Field(100.0, ge=0)
    #: Fraction of each velocity limit kept free inside the solve (the clamp keeps the rest).
    velocity_headroom: float = Field(0.02, ge=0, lt=1)
    #: Self-collision penalty on the proxies.
    w_collision: float = Field(20.0, ge=0)
    #: Clearance (m) the collision proxies must keep. 15 mm, not 8: the proxies are sampled points
    #: and ≤32-plane polytopes, so MuJoCo's exact meshes touch between points at smaller margins.
    collision_margin: float = Field(0.015, ge=0, le=0.1)
    # --- location-preserving targets (embody/retarget/targets.py) ---
    #: Blend each wrist target towards a landmark-anchored one near the face and body.
    location_preserving: bool = True
    #: Blend weight 1 when the human hand is within `anchor_near` body scales (shoulder widths)
    #: of a landmark, 0 beyond `anchor_far`, linear between.
    anchor_near: float = Field(0.5, ge=0.0, le=5.0)
    #: (1.5: a hand held before the belly, ~0.7 scales out, was anchored at half weight and the
    #: shape-fit target put it 4.4 cm too far forward of the robot's chest on a leaning signer.)
    anchor_far: float = Field(1.5, gt=0.0, le=5.0)
    #: Softness (body scales) of the soft-min over (hand point, landmark) anchors: targets stay
    #: smooth when the nearest landmark changes.
    anchor_softness: float = Field(0.15, gt=0.0, le=1.0)
    #: Position residual on the anchored robot hand points (palm centre, finger tips;
    #: embody/retarget/hand_points.py), times each point's anchoring weight: the point that carries
    #: the sign (a fingertip at the chin) lands on the robot's landmark, not only the wrist. 0: off.
    w_hand_points: float = Field(40.0, ge=0)
    #: Its weight where a point is anchored but not touching (within `anchor_far`, beyond
    #: `touch_radius`): the wrist target already carries the location there.
    w_hand_points_near: float = Field(2.0, ge=0)
    #: A hand point within this many body scales of a landmark touches it: full `w_hand_points`,
    #: and the wrist pose terms released by `touch_release` (smoothstep to 0 at this distance).
    touch_radius: float = Field(0.2, gt=0.0, le=1.0)
    #: Softness (body scales) of the share between hand points: a point this much further from
    #: the body than the nearest one gets e⁻¹ of its weight (the touching point dominates; the
    #: robot's other finger proportions must not pull it off the landmark).
    hand_point_softness: float = Field(0.05, gt=0.0, le=1.0)
    #: A touching hand point is aimed this far (m) from its landmark, along the human's offset:
    #: the touch ends where the self-collision term stops it (`collision_margin` between the
    #: proxies, which are larger than MuJoCo's meshes), never inside (see hand_points.py).
    touch_clearance: float = Field(0.015, ge=0.0, le=0.1)
    #: Share of the wrist pose terms released where a hand point is fully anchored: the robot's
    #: hand differs, so the human's wrist pose and the anchored point conflict; the point wins.
    touch_release: float = Field(1.0, ge=0.0, le=1.0)
    #: Wrist orientation weight where a hand point touches (instead of `w_wrist_rot`): the
    #: anchored points would otherwise twist the palm (palm orientation is part of the sign).
    w_wrist_rot_touch: float = Field(0.5, ge=0)
    #: Hinge keeping the robot's hands apart where the human's are apart, at hand scale
    #: (embody/retarget/hand_clearance.py): G1's Dex3 hands are 1.4 human hands long on an arm
    #: span 0.76 of the human's, so without it hands passing near each other touch. 0: off.
    w_hand_clearance: float = Field(20.0, ge=0)
    #: The human's hands touch within this gap (m; the fidelity measure's `contact_eps`): no
    #: clearance is asked for there, the collision margin makes the touch.
    hand_contact_eps: float = Field(0.015, gt=0.0, le=0.1)
    #: The most hand-hand clearance (m) asked for: enough to read as "apart".
    hand_gap_max: float = Field(0.05, gt=0.0, le=0.5)
    # --- solver (Levenberg-Marquardt over the banded whole-sequence system) ---
    #: FK backend of the solver's residuals and geometric Jacobians: the pytorch-kinematics chain
    #: (cut down to the bodies the costs use, all frames in one batched call per iteration) or the
    #: NumPy `KinematicTree`. Both give the same FK (≤1e-9 m, ~1e-15 in practice) and the same
    #: solution (tested). pk is the default because it costs little (the tree is ~1.2× faster,
    #: within the 1.5× accepted for solving on the real pk kinematics); "tree" is the fast path.
    kinematics: Literal["pytorch_kinematics", "tree"] = "pytorch_kinematics"
    #: Cold start: iterations that track with only `tracking_collision` before the full term comes on.
    tracking_iterations: int = Field(12, ge=0, le=10_000)
    #: Collision weight of the tracking phase, as a fraction of `w_collision`. A faint penalty
    #: (1e-3) leaves the way to the targets free but stops hands from being planted inside each
    #: other, which the full term cannot undo later (0 leaves more contacts; stronger ones make
    #: hands block each other on their way out of the rest pose).
    tracking_collision: float = Field(0.001, ge=0, le=1)
    #: Cold start, between tracking and the full term: `ramp_iterations` at this fraction of
    #: `w_collision`: a continuation step that tracks closer and smoother than a longer tracking
    #: phase alone. 0 iterations: no ramp.
    ramp_collision: float = Field(0.1, ge=0, le=1)
    ramp_iterations: int = Field(6, ge=0, le=10_000)
    #: Cold start: the tracking and ramp phases run on every `coarse_stride`-th frame of a 30 fps
    #: clip (the same time step at other rates), and their interpolation starts the full phase on
    #: every frame. 1: every phase on every frame.
    coarse_stride: int = Field(2, ge=1, le=8)
    #: Iterations with every term on (the only phase when warm-started).
    iterations: int = Field(24, ge=1, le=10_000)
    #: Polish phase after the full one (cold or warm): where the proxies press, they make way for
    #: MuJoCo's exact contacts (`retarget.exact_contacts`) at `polish_margin`, so hands and arms may
    #: come as close to each other and the body as the targets ask. Off by default: closer
    #: tracking near contact for ~1.5× the solve's CPU time. 0: no polish.
    polish_iterations: int = Field(0, ge=0, le=10_000)
    #: Clearance (m) the polish phase keeps between MuJoCo's collision geoms (counted pairs only).
    polish_margin: float = Field(0.002, ge=0, le=0.05)
    #: The polish asks MuJoCo about the frames (± `polish_pad`) where a proxy pair is inside the
    #: proxies' margin and a wrist is more than `polish_near` (m) off its target; the other frames
    #: keep the proxies' rows (MuJoCo is the costly part; 0.003 halves its frames, same accuracy).
    polish_near: float = Field(0.003, ge=0, le=0.1)
    polish_pad: int = Field(2, ge=0, le=1000)
    #: Factor on `w_smooth`/`w_jerk` in the polish phase (the basin is chosen): lower tracks
    #: closer for more jerk.
    polish_smooth: float = Field(1.0, ge=0, le=1)
    #: Contact phase after the solve (`ik.resolve_contacts`): where MuJoCo finds the proxies leaked
    #: (a counted contact), up to `contact_rounds` LM phases of `contact_iterations` each with
    #: MuJoCo's own contacts at `contact_margin` and weight `w_contact` on those frames (±
    #: `contact_pad`), so the contact is resolved jointly with tracking and smoothness instead
    #: of by the per-frame push of the repair, which turns joints by tens of degrees. 0 rounds:
    #: off.
    contact_rounds: int = Field(3, ge=0, le=100)
    contact_iterations: int = Field(30, ge=1, le=10_000)
    contact_pad: int = Field(3, ge=0, le=1000)
    w_contact: float = Field(2000.0, ge=0)
    #: Clearance (m) the contact phase asks between MuJoCo's geoms (the polish's 2 mm); a wider
    #: one costs location agreement without calming the export's repair.
    contact_margin: float = Field(0.002, ge=0, le=0.05)
    #: The contact phase moves only the frames within this many frames of a contact (the next
    #: `ik.HELD` held, the rest untouched): its cost scales with the contacts, not the sequence.
    contact_window: int = Field(10, ge=0, le=100_000)
    #: Also check (and resolve) the control-rate samples between frames (`control_rate_hz`): hands
    #: that pass through each other between two clear frames are otherwise found only by the
    #: export, whose per-sample repair can turn the arms far from the solve.
    contact_samples: bool = True
    #: End a contact round at the first accepted step after which MuJoCo finds nothing touching
    #: on the window's frames and samples (velocity-clamped, as exported); the first round not
    #: on `tolerance` (later ones still): the rounds' LM steps oscillate round the contact set
    #: (each costing MuJoCo rows at every checked frame and sample), and a first round stopped on
    #: the tolerance with contacts left handed them to the repair. Off: rounds run to the
    #: tolerance or `contact_iterations`.
    contact_stop: bool = True
    #: End a contact round, and the contact phase, when MuJoCo's deepest penetration on the
    #: checked frames and samples has not improved by `contact_stall_mm` over the last
    #: `contact_stall` evaluations: a contact the window cannot route round (interlocked
    #: fingers) is the repair's, and rounds spent on it are wasted. A round whose rows are clear
    #: while the velocity-clamped trajectory still touches ends, but the phase goes on: the next
    #: round's rows start from the clamped q and see what the clamp moved in. 0: off.
    contact_stall: int = Field(6, ge=0, le=10_000)
    contact_stall_mm: float = Field(0.5, ge=0, le=100)
    #: The contact phase's samples between frames also get the proxies' rows (hinged at
    #: `contact_sample_margin`), not only MuJoCo's: MuJoCo's rows exist only for pairs already
    #: within `contact_margin`, so a step that cleared one pair ran into the next and was
    #: rejected; the proxies see a pair coming (fewer LM evaluations and MuJoCo calls).
    contact_sample_proxies: bool = True
    #: Clearance (m) the proxies' rows at samples ask (≤ the proxies' `collision_margin`): the
    #: full margin pushes hands apart between frames.
    contact_sample_margin: float = Field(0.008, ge=0, le=0.05)
    #: Stop a phase once an accepted step lowers the cost by less than this fraction.
    tolerance: float = Field(3e-3, ge=0, le=1)
    # --- output ---
    #: Retarget fingers (robots without hands skip it).
    hands: bool = True
    #: Keep the finger targets within the hand joints' velocity limits (`hands.rate_limit`, symmetric
    #: in time) before the IK, so the arms are placed around the fingers the clamp will leave: a
    #: jittering human hand otherwise flips the thumb faster than it can move, the clamp rewrites
    #: it after the solve and the contact repair untangles what it then touches.
    hand_rate_limit: bool = True
    #: Keep each hand's fingers out of each other and out of their palm (`finger_clearance`):
    #: a handshape that would need them through each other is met as closely as the hand allows.
    hand_self_clearance: bool = True
    #: Clamp per-step joint changes to the velocity limits at the trajectory's fps.
    enforce_velocity_limits: bool = True
    #: Remove what MuJoCo still finds penetrating after the solve (the proxies leak between
    #: sampled points and at interpolated control samples), at both rates (`retarget.control`).
    #: Off only to study the proxies alone.
    contact_repair: bool = True
    control_rate_hz: float = Field(50.0, gt=0, le=2000)
    #: The exported control-rate array honours the motors' effort limits and keeps the standing
    #: robot's ZMP inside its feet (`retarget.dynamics_limits`: the kinematic chain's path is
    #: kept and retimed, slowed down locally where a sample asks too much; each sample's source
    #: time is stored beside it). A trajectory already inside every limit is left exactly as it
    #: is. Off only to study the kinematic chain alone.
    dynamics_limits: bool = True
    #: Share (dimensionless, of N·m) of each joint's effort limit (the MJCF's `actuatorfrcrange`,
    #: fingers included) the inverse-dynamics torque of every exported sample may use: fixed base,
    #: free motion, velocities and accelerations of the natural cubic spline through the samples
    #: at `control_rate_hz` (the curve the exported q/qd commands play), plus the joints' dry
    #: friction (`robot.dynamics.inverse_dynamics`). The rest is left to the tracking controller.
    torque_limit_fraction: float = Field(0.9, gt=0.0, le=1.0)
    #: Distance (m) the cart-table ZMP of the robot standing on both feet (legs at the stance pose,
    #: `robot.dynamics.zmp`) keeps inside the feet's support polygon at every exported sample.
    zmp_margin: float = Field(0.02, ge=0.0, le=0.1)
    #: Longer sequences are solved in windows of this many frames sharing `window_overlap`
    #: frames (cross-faded), so the solver's memory is bounded by the window (embody.retarget.windows).
    window_frames: int = Field(2000, ge=16, le=1_000_000)
    window_overlap: int = Field(50, ge=2, le=10_000)

    @model_validator(mode="after")
    def _ik_overlap_fits(self) -> "IKConfig":
        check_window(self.window_frames, self.window_overlap)
        return self
