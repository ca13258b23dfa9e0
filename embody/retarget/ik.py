"""Whole-sequence IK: all frames solved jointly, Levenberg-Marquardt over a banded system.

Cost (summed over frames, see `costs.py`): wrist position + orientation, soft elbow position,
optional torso/head orientation, the proxy self-collision penalty, a posture prior towards the
robot's rest pose (stronger on the waist: the torso stays upright unless the arms need it), a
hinge on joint speeds past the velocity limits, plus Δ²q (and optionally Δ³q, `w_jerk`) smoothness coupling the frames.

A cold start continues from a faint to a partial to the full collision term, its first two
phases on every second frame (coarse to fine, `IKConfig.coarse_stride`). An optional polish
phase (`IKConfig.polish_iterations`) then swaps the proxies for MuJoCo's exact contacts where
they press (`exact_contacts.py`), so the 15 mm proxy margin no longer costs wrist accuracy.
Where MuJoCo still finds a contact, on a frame or on a control-rate sample between two, a
contact phase (`resolve_contacts`) resolves it on a window round it with the edges held.

Frames couple only through the smoothness and velocity terms, so the normal matrix is banded and
one LAPACK call (`banded.block_banded_solve`) solves all frames jointly in O(T·n³). Steps
are clamped to the joint box, so limits are never violated. Residuals are NumPy with geometric
Jacobians from one batched FK pass per iteration (`cfg.kinematics`: pytorch-kinematics or the
NumPy tree), computed only for accepted steps. A final clamp (`limits.clamp_velocity`) removes
what the soft velocity hinge leaves; then MuJoCo's exact contacts are removed where the proxies
leaked (`control.separate`), at the source rate and at the control rate (`control_trajectory`:
the array the library exports), and the result carries MuJoCo's contact count in its metrics.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from embody.config.ik import IKConfig
from embody.metrics.trajectory import mean_jerk, position_error, rotation_error_deg
from embody.motion import WEIGHT_FPS, smoothness_scale
from embody.retarget.banded import block_banded_solve
from embody.retarget.costs import WRIST_ELBOW, Residuals
from embody.retarget.control import bridge_contacts_checked, control_trajectory_checked, separate_checked
from embody.retarget.dynamics_limits import DynamicsLimits, uniform_time
from embody.retarget.exact_contacts import ExactContacts
from embody.retarget.limits import clamp_velocity, limit_violations, velocity_violations
from embody.retarget.targets import _ARRAYS, Targets
from embody.retarget.validation import validation_counts
from embody.robot import Robot
from embody.robot.contacts import self_collision_contacts


@dataclass
class IKSolution:
    """Joint trajectory at source fps and at the control rate, with per-frame and aggregate metrics."""

    q: np.ndarray
    joint_names: list[str]
    fps: float
    q_control: np.ndarray
    control_rate_hz: float
    frame_metrics: dict[str, np.ndarray]
    metrics: dict[str, float] = field(default_factory=dict)
    #: (N,) each `q_control` sample's time (s) on the source's timeline: k / rate unless the
    #: torque and ZMP limits slowed the motion down there (`dynamics_limits.retime_dynamics`).
    source_time: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.source_time is None:
            self.source_time = uniform_time(len(self.q_control), self.control_rate_hz)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"q": self.q, "q_control": self.q_control, "source_time": np.asarray(self.source_time),
                **{f"frame_{k}": v for k, v in self.frame_metrics.items()}}

    def to_attrs(self) -> dict[str, Any]:
        return {"joint_names": list(self.joint_names), "fps": self.fps,
                "control_rate_hz": self.control_rate_hz, "metrics": dict(self.metrics)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "IKSolution":
        frames = {k[len("frame_"):]: np.asarray(v) for k, v in arrays.items() if k.startswith("frame_")}
        return cls(q=np.asarray(arrays["q"]), joint_names=list(attrs["joint_names"]), fps=float(attrs["fps"]),
                   q_control=np.asarray(arrays["q_control"]), control_rate_hz=float(attrs["control_rate_hz"]),
                   frame_metrics=frames, metrics=dict(attrs["metrics"]),
                   source_time=np.asarray(arrays["source_time"]) if "source_time" in arrays else None)


def _difference_normal(t: int, order: int = 2) -> np.ndarray:
    """Diagonals (order+1, t) of DᵀD for the `order`-th difference operator D ((t-order)×t), zero-padded."""
    c = np.array([1.0])
    for _ in range(order):
        c = np.convolve(c, [1.0, -1.0])
    out = np.zeros((order + 1, t))
    rows = np.arange(max(t - order, 0))
    for a in range(order + 1):  # row i of D has c at columns i … i+order
        for k in range(order + 1 - a):
            np.add.at(out[k], rows + a, c[a] * c[a + k])
    return out


#: Initial Marquardt damping, carried across phases: the first Gauss-Newton step from the rest
#: pose overshoots badly, and a phase change needs no fresh start.
LAMBDA0 = 1.0
#: Smallest damping after a rejected step, and at the start of a phase. The damping is
#: relative (Marquardt's scaling); a converged phase leaves it near Gauss-Newton (1e-7), and
#: the next phase's first step (a heavier collision term, all frames after the coarse pass)
#: overshoots: doubling from there took 5-10 rejected trials, each a full residual evaluation,
#: before a step was accepted (benchmarks/ik_vs_mink.py: 162 evaluations for 109 accepted
#: steps). With the floor: 1.13× CPU frames/s, same accuracy.
LAMBDA_MIN = 1e-3


def _dilate(mask: np.ndarray, pad: int) -> np.ndarray:
    """(T,) bool: the frames within `pad` frames of a True one in `mask`."""
    idx = np.flatnonzero(mask)
    cover = np.zeros(len(mask) + 2 * pad + 1, dtype=np.int64)  # +1 from idx − pad, −1 after idx + pad
    np.add.at(cover, idx, 1)
    np.subtract.at(cover, idx + 2 * pad + 1, 1)
    return np.cumsum(cover)[pad: pad + len(mask)] > 0


def coarse_stride(stride: int, fps: float) -> int:
    """The cold start's stride in frames at `fps`: `stride` at 30 fps, the same time step at
    other rates (a 120 fps clip with stride 2 starts from a 60 fps grid, whose cold phases do
    not reach the basin the 15 fps one does)."""
    return max(1, int(round(stride * fps / WEIGHT_FPS)))


class _Problem:
    """½‖r(q)‖² + ½Σ w_post·(q − q_rest)² + ½·w_smooth‖Δ²q‖² + ½·w_jerk‖Δ³q‖² over the IK joints
    of every frame."""

    def __init__(self, robot: Robot, targets: Targets, cfg: IKConfig) -> None:
        self.robot, self.cfg = robot, cfg
        self.residuals = Residuals(robot, targets, cfg)
        self.ik = self.residuals.ik
        t = targets.num_frames
        base = np.tile(robot.rest, (t, 1))
        if targets.hand_joints and cfg.hands:
            cols = [robot.joint_index(n) for n in targets.hand_joints]
            base[:, cols] = np.clip(targets.hand_q, robot.lower[cols], robot.upper[cols])
        self.base = base
        self.rest = robot.rest[self.ik]
        waist = np.array([robot.joint_names[j] in robot.waist_joint_names for j in self.ik])
        self.w_post = np.where(waist, cfg.w_waist_posture, cfg.w_posture)
        # Δ²q (acceleration) and Δ³q (jerk, what `mean_jerk` measures) penalties, one band
        self.dtd = np.zeros((4, t))
        self.dtd[:3] += _difference_normal(t, 2) * cfg.w_smooth * smoothness_scale(targets.fps, 2)
        self.dtd += _difference_normal(t, 3) * cfg.w_jerk * smoothness_scale(targets.fps, 3)
        self.dtd_polish = self.dtd * cfg.polish_smooth  # the polish phase's (the basin is chosen)
        #: per-step joint change allowed by the velocity limits, with a little headroom
        self.step_limit = robot.velocity_limits[self.ik] / targets.fps * (1.0 - cfg.velocity_headroom)
        #: the velocity hinge's weight at this rate (a per-step excess shrinks as dt, like Δ¹q)
        self.w_velocity = cfg.w_velocity * smoothness_scale(targets.fps, 1)
        #: (T,) bool frames held where they are (the edges of a windowed contact phase), or None
        self.held: np.ndarray | None = None

    def q_full(self, qi: np.ndarray) -> np.ndarray:
        q = self.base.copy()
        q[:, self.ik] = qi
        return q

    def _smooth_grad(self, qi: np.ndarray) -> np.ndarray:
        """(w_s·DᵀD) qi, from the band's diagonals."""
        g = self.dtd[0][:, None] * qi
        for k in (1, 2, 3):
            if len(qi) > k:
                g[:-k] += self.dtd[k, : len(qi) - k, None] * qi[k:]
                g[k:] += self.dtd[k, : len(qi) - k, None] * qi[:-k]
        return g

    def evaluate(self, qi: np.ndarray, collision: float, exact: bool = False,
                 bound: float | None = None) -> tuple[float, Callable[[], tuple] | None]:
        """Cost now; on demand, the Gauss-Newton blocks (per-frame JᵀJ (T,n,n), velocity-hinge
        diagonal (T,n) and off-diagonal (T-1,n)) and the gradient (T,n), linear terms included.
        `exact`: MuJoCo's contacts instead of the proxies (the polish phase). `bound`: a trial
        whose cost is certainly above it comes back as (inf, None) as soon as that is known,
        without the rest of its rows (`Residuals.lazy(limit=)`): the solver rejects it either way."""
        dq = qi - self.rest
        sg = self._smooth_grad(qi)
        d = np.diff(qi, axis=0)
        over = np.maximum(np.abs(d) - self.step_limit, 0.0)  # velocity hinge: only past the limit
        post, smooth, vel = (self.w_post * dq**2).sum(), (qi * sg).sum(), self.w_velocity * (over**2).sum()
        limit = None
        if bound is not None:  # the rows' sum of squares above which the cost exceeds the bound
            linear = float(post + smooth + vel)
            limit = 2.0 * bound - linear + 1e-9 * (2.0 * abs(bound) + abs(linear))  # slack ≫ rounding
            if limit < 0.0:  # the linear terms alone: no FK needed
                return np.inf, None
        r, jac = self.residuals.lazy(self.q_full(qi), collision=collision, exact=exact, limit=limit)
        if r is None:
            return np.inf, None
        cost = 0.5 * float((r**2).sum() + post + smooth + vel)

        def normal() -> tuple[tuple[np.ndarray, ...], np.ndarray]:
            j = jac()
            jt = np.swapaxes(j, 1, 2)
            g = (jt @ r[..., None])[..., 0] + self.w_post * dq + sg
            gv = self.w_velocity * over * np.sign(d)
            g[1:] += gv
            g[:-1] -= gv
            active = self.w_velocity * (over > 0)
            vdiag = np.zeros_like(qi)
            vdiag[1:] += active
            vdiag[:-1] += active
            return (jt @ j, vdiag, -active), g

        return cost, normal

    def step(self, h: tuple[np.ndarray, ...], g: np.ndarray, lam: float) -> np.ndarray:
        """Solve (JᵀJ + W_post + W_vel + λ·diag + w_s·DᵀD⊗I) δ = −g for all frames at once."""
        jtj, vdiag, voff = h
        t, n, _ = jtj.shape
        eye = np.eye(n)
        diag = jtj + (self.w_post + vdiag + lam * self.damping(h) + self.dtd[0][:, None])[:, :, None] * eye
        offs = [self.dtd[1, : t - 1, None] + voff]
        offs += [np.repeat(self.dtd[k, : max(t - k, 0), None], n, 1) for k in (2, 3)]
        if not self.dtd[3].any():
            offs.pop()  # pentadiagonal: a narrower band
        if self.held is not None:  # δ = 0 there: the free frames solve with their held neighbours fixed
            diag[self.held] = eye * 1e12
            g = np.where(self.held[:, None], 0.0, g)
            return np.where(self.held[:, None], 0.0, -block_banded_solve(diag, offs, g))
        return -block_banded_solve(diag, offs, g)

    def damping(self, h: tuple[np.ndarray, ...]) -> np.ndarray:
        """Marquardt's scaling: the diagonal of the Gauss-Newton matrix (T,n)."""
        return np.diagonal(h[0], axis1=1, axis2=2) + self.w_post + h[1] + 1e-9

    def _polish_frames(self, qi: np.ndarray) -> np.ndarray:
        """Frames (T,) bool the polish hands to MuJoCo: within `polish_pad` frames of one where a
        proxy pair is inside the proxies' margin and a wrist is over `polish_near` off its target."""
        r, _ = self.residuals.lazy(self.q_full(qi), collision=1.0)
        pressed = r[:, self.residuals.n_task_rows:].max(1, initial=0.0) > 0
        wrist = np.linalg.norm(r[:, :6].reshape(len(r), 2, 3), axis=-1).max(1)
        return _dilate(pressed & (wrist > self.cfg.polish_near), self.cfg.polish_pad)

    def solve(self, qi0: np.ndarray, cold: bool, full: bool = True, lam: float = LAMBDA0,
              contact_frames: np.ndarray | None = None,
              contact_between: tuple[np.ndarray, np.ndarray] | None = None,
              clear: Callable[[np.ndarray], bool] | None = None,
              contact_proxies: tuple[np.ndarray, np.ndarray] | None = None,
              tolerance_stop: bool = True) -> np.ndarray:
        """Levenberg-Marquardt (Nielsen's damping rule). From a cold start the collision term comes
        on in full after a tracking phase: with it on from the rest pose, hands block each other and
        the trunk on their way to the targets (3× the wrist error on the synthetic set). Without it
        there, hands get planted deep inside each other (thumbs interlocked) and stay locked, so the
        tracking phase keeps a faint share of it (`cfg.tracking_collision`). A short intermediate
        phase (`cfg.ramp_collision`) then lets hands that meet slide round each other before the
        full term fixes them in place (a continuation; 4.46 → 3.85 mm all-frame wrist error on
        benchmarks/ik_vs_mink.py's 4 sequences, lower jerk, still 0 contacts). `full=False` stops
        after the cold phases (the coarse pass of `solve_joints`); `lam` is the starting damping.
        `contact_frames` (T,) bool: only the exact-contact phase, on those frames (`resolve_contacts`);
        `contact_between` (frame, fraction) arrays: also on those samples between frames; `clear`
        (qi → bool, MuJoCo's verdict): the contact phase stops at the first accepted step that
        leaves no MuJoCo row penetrating and that `clear` passes (on the tolerance only with
        `tolerance_stop`);
        `contact_proxies` (frame, fraction) arrays: the proxies' rows at those samples too."""
        lower, upper = self.robot.lower[self.ik], self.robot.upper[self.ik]
        qi = np.clip(qi0, lower, upper)
        self.stalled = False
        use_col = self.residuals.proxies is not None
        phases = []
        if cold and use_col:  # continuation: faint → partial → full collision weight
            phases = [(self.cfg.tracking_collision, self.cfg.tracking_iterations)]
            if self.cfg.ramp_iterations:
                phases.append((self.cfg.ramp_collision, self.cfg.ramp_iterations))
        if full or not phases:
            phases.append((float(use_col), self.cfg.iterations))
        phases = [(c, n, False) for c, n in phases]
        if full and self.residuals.exact is not None:
            phases.append((1.0, self.cfg.polish_iterations, True))
        if contact_frames is not None:
            phases = [(1.0, self.cfg.contact_iterations, True)]
        smooth = self.dtd
        for collision, budget, exact in phases:
            self.dtd = self.dtd_polish if exact else smooth
            if exact:
                self.residuals.exact.frames = (self._polish_frames(qi) if contact_frames is None
                                               else contact_frames)
                self.residuals.exact.between = contact_between
                self.residuals.sample_points = contact_proxies
            cost, normal = self.evaluate(qi, collision, exact)
            h, g = normal()
            nu = 2.0
            lam = max(lam, LAMBDA_MIN)
            watch = exact and clear is not None and self.cfg.contact_stall > 0
            best, since = (self.residuals.exact.deepest, 0) if watch else (0.0, 0)
            deepest = best  # MuJoCo's deepest distance over the rows' poses at qi
            for _ in range(budget):
                step = self.step(h, g, lam)
                cand = np.clip(qi + step, lower, upper)
                c_new, normal = self.evaluate(cand, collision, exact, bound=cost)
                predicted = 0.5 * float((step * (lam * self.damping(h) * step - g)).sum())
                if c_new < cost:
                    rho = (cost - c_new) / max(predicted, 1e-300)
                    done = cost - c_new < self.cfg.tolerance * cost
                    qi, cost = cand, c_new
                    if watch:
                        deepest = self.residuals.exact.deepest
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                    if exact and clear is not None:
                        # a contact round ends when MuJoCo finds it clear; on the tolerance only
                        # when `tolerance_stop`: its steps stall at a high damping round the
                        # contact set, and a first round stopped there left the contacts to the
                        # repair (benchmark seq 0, s11)
                        done = ((done and tolerance_stop)
                                or (self.residuals.exact.deepest >= 0 and clear(qi)))
                    if done:
                        break
                    h, g = normal()
                    if watch and self.residuals.exact.deepest > best + self.cfg.contact_stall_mm * 1e-3:
                        best, since = self.residuals.exact.deepest, -1
                else:
                    lam = max(lam * nu, LAMBDA_MIN)
                    nu *= 2.0
                    if lam > 1e8:
                        break
                since += 1
                if watch and since >= self.cfg.contact_stall:
                    # MuJoCo's deepest contact no longer improves. Stalled only while the rows
                    # still penetrate: with them clear and `clear` failing, the contact is the
                    # velocity clamp's (it moves the rows' poses; the next round's rows start
                    # from the clamped q and see it)
                    self.stalled = deepest < 0
                    break
        self.dtd = smooth
        self.residuals.sample_points = None
        self.lam = lam  # where the damping ended: a finer solve of the same problem goes on from it
        return qi


def evaluate(robot: Robot, q: np.ndarray, targets: Targets,
             contacts: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per-frame tracking metrics of q against targets, their aggregates, and MuJoCo's verdict
    (`contacts` (T,): MuJoCo's per-frame contact counts of exactly this q, when already known)."""
    pos, rot = robot.link_poses(q, WRIST_ELBOW)
    wrist = position_error(pos[:, :2], targets.wrist_pos) * 1000.0
    frames = {
        "wrist_pos_err_mm": wrist,
        "wrist_rot_err_deg": rotation_error_deg(rot[:, :2], targets.wrist_rot),
        "elbow_pos_err_mm": position_error(pos[:, 2:4], targets.elbow_pos) * 1000.0,
        "self_contacts": self_collision_contacts(robot, q) if contacts is None else np.asarray(contacts),
    }
    fps = targets.fps
    limits = float(limit_violations(q, robot.lower, robot.upper))
    velocity = float(velocity_violations(q, robot.velocity_limits, fps))
    metrics = {
        "frames": float(len(q)),
        "wrist_pos_err_mm": float(wrist.mean()),
        "wrist_pos_mean_mm": float(wrist.mean()),
        "wrist_pos_p95_mm": float(np.percentile(wrist, 95)),
        "wrist_pos_err_max_mm": float(wrist.max()),
        "wrist_pos_err_rel": float(wrist.mean() / 1000.0 / targets.arm_length),
        "wrist_rot_err_deg": float(frames["wrist_rot_err_deg"].mean()),
        "wrist_rot_mean_deg": float(frames["wrist_rot_err_deg"].mean()),
        "elbow_pos_err_mm": float(frames["elbow_pos_err_mm"].mean()),
        "joint_limit_violations": limits,
        "limit_violations": limits,
        "velocity_violations": velocity,
        "jerk": mean_jerk(q[:, robot.ik_mask], fps),
        "self_collision_frames": float((frames["self_contacts"] > 0).sum()),
        "self_contacts": float(frames["self_contacts"].sum()),
    }
    return frames, metrics


def same_problem(a: Targets, b: Targets) -> bool:
    """Whether two target sets give the solver exactly the same problem, so one solve serves both
    (the pipeline's IK-only fidelity baseline is the retarget step's solve wherever location
    preservation anchored nothing). The solver reads the arrays below and, only where a point
    weight is positive, the anchored hand points (`hand_points.hand_point_term`)."""
    if (a.fps, list(a.hand_joints), a.arm_length) != (b.fps, list(b.hand_joints), b.arm_length):
        return False
    for k in (k for k in _ARRAYS if not k.startswith("point_")):  # every per-frame array the solver reads
        if not np.array_equal(np.asarray(getattr(a, k)), np.asarray(getattr(b, k))):
            return False
    active = [np.size(t.point_weight) > 0 and bool(np.any(np.asarray(t.point_weight) > 0)) for t in (a, b)]
    if not any(active):
        return True
    return (all(active) and list(a.point_names) == list(b.point_names)
            and np.array_equal(a.point_pos, b.point_pos) and np.array_equal(a.point_weight, b.point_weight))


def solve_joints(robot: Robot, targets: Targets, cfg: IKConfig,
                 init: IKSolution | np.ndarray | None = None) -> np.ndarray:
    """The optimiser alone (its contact phase, `resolve_contacts`, included): joint trajectory
    (T, n_joints) inside the joint box, before the velocity clamp, the MuJoCo repair and the
    verification that `solve` adds."""
    return _solve_joints_checked(robot, targets, cfg, init)[0]


def _solve_joints_checked(robot: Robot, targets: Targets, cfg: IKConfig,
                          init: IKSolution | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """`solve_joints`, and the frames (T,) where MuJoCo finds a counted contact in it (None when
    the contact phase did not check)."""
    problem = _Problem(robot, targets, cfg)
    t = targets.num_frames
    q0 = init.q if isinstance(init, IKSolution) else init
    if q0 is not None and np.shape(q0) == (t, robot.n_joints):
        qi = problem.solve(np.asarray(q0, dtype=np.float64)[:, problem.ik], cold=False)
    elif (s := coarse_stride(cfg.coarse_stride, targets.fps)) > 1 and t >= 4 * s \
            and problem.residuals.proxies is not None:
        # coarse to fine: the cold phases on every s-th frame (a grid at 30 / `coarse_stride`
        # fps whatever the input rate), interpolated, then the full phase on every frame.
        # `_Problem` rescales the smoothness to the coarse grid's rate; the extra factor
        # `coarse_stride` makes the cold phases that much smoother than the full one, so the
        # basin they choose is a smooth one (and its square keeps the velocity hinge per step).
        c = cfg.coarse_stride
        idx = np.unique(np.r_[np.arange(0, t, s), t - 1])
        coarse_targets = replace(targets, fps=targets.fps / s, **{k: getattr(targets, k)[idx] for k in _ARRAYS})
        coarse_cfg = cfg.model_copy(update={"w_smooth": cfg.w_smooth * c, "w_jerk": cfg.w_jerk * c,
                                            "w_velocity": cfg.w_velocity * c**2})
        coarse = _Problem(robot, coarse_targets, coarse_cfg)
        qc = coarse.solve(np.tile(robot.rest[problem.ik], (len(idx), 1)), cold=True, full=False)
        frames = np.arange(t)
        qi0 = np.stack([np.interp(frames, idx, qc[:, j]) for j in range(qc.shape[1])], 1)
        qi = problem.solve(qi0, cold=False, lam=coarse.lam)
    else:
        qi = problem.solve(np.tile(robot.rest[problem.ik], (t, 1)), cold=True)
    return resolve_contacts_checked(robot, targets, cfg, robot.clip(problem.q_full(qi)))


#: Frames held at each edge of a contact window: Δ³q (the widest difference) reaches 3 frames,
#: so with 3 held the windowed problem is the whole one with the frames outside fixed.
HELD = 3


def _between(n: int, fps: float, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """The control-rate samples (`limits.resample`) strictly between source frames: each one's
    frame t and fraction α ((1 − α)·q_t + α·q_t+1)."""
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0)
    s = np.arange(int(np.floor((n - 1) / fps * rate + 1e-9)) + 1) * (fps / rate)
    t = np.minimum(np.floor(s + 1e-9).astype(np.int64), n - 2)
    a = s - t
    keep = (a > 1e-9) & (a < 1.0 - 1e-9)
    return t[keep], a[keep]


def _touching(robot: Robot, q: np.ndarray, frames: np.ndarray,
              between: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's verdict (counted contacts) on q's `frames` (T,) bool and on the samples `between`
    them whose two frames are both in `frames`: (T,) and (S,) bool, False where not checked."""
    hit, smp = np.zeros(len(q), dtype=bool), np.zeros(len(between[0]), dtype=bool)
    idx = np.flatnonzero(frames)
    hit[idx] = self_collision_contacts(robot, q[idx]) > 0
    t, a = between
    if len(t):
        k = np.flatnonzero(frames[t] & frames[t + 1])
        if len(k):
            x = (1.0 - a[k, None]) * q[t[k]] + a[k, None] * q[t[k] + 1]
            smp[k] = self_collision_contacts(robot, x) > 0
    return hit, smp


def resolve_contacts(robot: Robot, targets: Targets, cfg: IKConfig, q: np.ndarray) -> np.ndarray:
    """q (T,n) with the contacts the proxies leaked resolved inside the optimisation
    (`resolve_contacts_checked`)."""
    return resolve_contacts_checked(robot, targets, cfg, q)[0]


def resolve_contacts_checked(robot: Robot, targets: Targets, cfg: IKConfig,
                             q: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """q (T,n) with the contacts the proxies leaked resolved inside the optimisation, and MuJoCo's
    verdict on the returned frames (T,) bool as exported, i.e. after the velocity clamp (None
    when off: nothing checked; q comes back velocity-clamped when a round ran, else as it came). Where MuJoCo finds
    a counted contact on a frame or (`contact_samples`) on a control-rate sample between two
    frames (hands passing through each other between two clear frames, which the export's
    per-sample repair then pulls apart), an LM phase whose collision rows on those frames (± `cfg.contact_pad`) are
    MuJoCo's own contacts at `contact_margin`, weighted `w_contact` (a near-constraint), with
    every other term kept; repeated (`contact_rounds`) while contacts remain, each round adding
    the frames it finds. The phase runs on windows only: the frames within `contact_window` of a
    contact move, `HELD` frames beyond them are held, the rest are not touched (the cost scales
    with the contacts, not the sequence). Why: the repair after the solve (`control.separate`)
    pushes each frame apart alone and blends the push into its neighbours; on a deep leak (a
    thumb 30 mm inside the opposite shoulder during a SHOULDER sign) that moved the arms 30-80°
    for ±0.5 s and took the hand off its landmark. Here the smoothness and the targets share the
    correction, and the repair has little left to do."""
    if not cfg.contact_rounds or not cfg.contact_repair:
        return q, None
    none = (np.zeros(0, np.int64), np.zeros(0))
    between = _between(len(q), targets.fps, cfg.control_rate_hz) if cfg.contact_samples else none
    if cfg.enforce_velocity_limits:
        # MuJoCo judges the trajectory the export gets: `finish_solution` clamps the velocities
        # next, and the clamp alone put a 50 Hz sample back in touch (benchmark seq 2, s11)
        def exported(x: np.ndarray) -> np.ndarray:
            return clamp_velocity(x, robot.velocity_limits, targets.fps)
    else:
        def exported(x: np.ndarray) -> np.ndarray:
            return x
    hit, smp = _touching(robot, exported(q), np.ones(len(q), dtype=bool), between)
    contacts = hit.copy()
    if not hit.any() and not smp.any():
        return q, contacts  # as it came: the clamp after it finds it clear
    q = exported(q)
    sub_cfg = cfg.model_copy(update={"polish_iterations": 0})
    exact = ExactContacts(robot, cfg.contact_margin, cfg.w_contact)
    q = q.copy()
    found = int(hit.sum() + smp.sum())
    for round_ in range(cfg.contact_rounds):
        touch, near = hit.copy(), np.zeros(len(q), dtype=bool)
        near[between[0][smp]] = True
        touch |= near
        touch[between[0][smp] + 1] = True
        free = _dilate(touch, cfg.contact_window)
        idx = np.flatnonzero(_dilate(free, HELD))
        window = replace(targets, **{k: getattr(targets, k)[idx] for k in _ARRAYS})
        problem = _Problem(robot, window, sub_cfg)
        if problem.residuals.proxies is None:
            return q, contacts
        problem.residuals.exact = exact
        problem.held = ~free[idx]
        rows = _dilate(touch, cfg.contact_pad)
        # sample rows near a contact (a sample's or a frame's: the samples next to a touching
        # frame touched in the round after), between two frames with rows (inside one window)
        t, a = between
        pick = (_dilate(near | hit, cfg.contact_pad)[t] & rows[t] & rows[t + 1] if len(t)
                else np.zeros(0, bool))
        sub = (np.searchsorted(idx, t[pick]), a[pick])
        seen: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

        def judged(qi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """q with the window at qi (clamped as exported) and MuJoCo's verdict on its frames and
            samples that moved (the window's, and any the clamp carried past it); the others keep
            theirs."""
            key = qi.tobytes()
            if key not in seen:
                trial = q.copy()
                trial[idx] = robot.clip(problem.q_full(qi))
                trial = exported(trial)
                moved = _dilate(free | (np.abs(trial - q).max(1) > 1e-12), 1)
                seen[key] = (trial, *_touching(robot, trial, moved, between))
            return seen[key]

        def clear(qi: np.ndarray) -> bool:
            _, now, now_smp = judged(qi)
            return not now.any() and not now_smp.any()

        qi = problem.solve(q[idx][:, problem.ik], cold=False, contact_frames=rows[idx], contact_between=sub,
                           clear=clear if cfg.contact_stop else None,
                           contact_proxies=sub if cfg.contact_sample_proxies else None,
                           # later rounds work on what the first could not route round: where
                           # they stall, the repair takes over (synth seq 6's second round ran
                           # its whole budget for no progress)
                           tolerance_stop=round_ > 0)
        q, now, now_smp = judged(qi)
        contacts = now  # every earlier contact frame lies inside `free`, checked again
        if not now.any() and not now_smp.any():
            break
        if problem.stalled:  # the deepest contact stopped improving: another round would too
            break
        left = int(now.sum() + now_smp.sum())
        if left >= found:  # no progress: a pass the windows cannot route round (the repair's)
            break
        found = left
        hit |= now
        smp |= now_smp
    return q, contacts


def solve(robot: Robot, targets: Targets, cfg: IKConfig | None = None,
          init: IKSolution | np.ndarray | None = None) -> IKSolution:
    """Solve all frames jointly; `init` (previous solution or (T,n) q) warm-starts the solver."""
    cfg = cfg or IKConfig()
    q, contacts = _solve_joints_checked(robot, targets, cfg, init)
    return finish_solution(robot, q, targets, cfg, contacts=contacts)


def finish_solution(robot: Robot, q: np.ndarray, targets: Targets, cfg: IKConfig,
                    extra: dict[str, float] | None = None,
                    contacts: np.ndarray | None = None) -> IKSolution:
    """A solved trajectory (T,n) inside the joint box made into the solution every solve returns
    (whole or windowed): velocity clamp, MuJoCo contact repair, evaluation (with `extra` metrics)
    and the verified control-rate array. `contacts` (T,) bool: MuJoCo's verdict on exactly this
    q, when the contact phase already has it (not checked twice)."""
    touching = None
    if cfg.contact_repair:  # short contact runs: their clear neighbours bound a local answer
        q, touching = bridge_contacts_checked(robot, q, fps=targets.fps if cfg.enforce_velocity_limits else None,
                                              bad=contacts)
    if cfg.enforce_velocity_limits:
        clamped = clamp_velocity(q, robot.velocity_limits, targets.fps)
        if not np.array_equal(clamped, q):
            touching = None  # the verdict was on the unclamped q
        q = clamped
    # MuJoCo has the last word at both rates: every written sample is collision-free
    clear = False
    if cfg.contact_repair:
        q, clear = separate_checked(robot, q, targets.fps, enforce_velocity=cfg.enforce_velocity_limits,
                                    touching=touching)
    frames, metrics = evaluate(robot, q, targets, np.zeros(len(q), np.int64) if clear else None)
    metrics.update(extra or {})
    q_control, clear, source_time = exported_control(robot, q, targets.fps, cfg)
    metrics.update(control_counts(robot, q_control, cfg.control_rate_hz, clear))
    return IKSolution(q=q, joint_names=list(robot.joint_names), fps=targets.fps, q_control=q_control,
                      control_rate_hz=cfg.control_rate_hz, frame_metrics=frames, metrics=metrics,
                      source_time=source_time)


def without_dynamics_limits(cfg: IKConfig) -> IKConfig:
    """`cfg` for a solve whose control-rate array is not the one exported (a critic round before
    the choice, a comparison baseline): its array is the kinematic chain's alone (resample,
    joint box, velocity limits, MuJoCo contacts), without the torque and ZMP retiming
    (`retarget.dynamics_limits`), which runs once, on the array that is exported
    (`exported_control`). The source-rate solve `q` is the same either way."""
    return cfg.model_copy(update={"dynamics_limits": False}) if cfg.dynamics_limits else cfg


def exported_control(robot: Robot, q: np.ndarray, fps: float, cfg: IKConfig,
                     kinematic: np.ndarray | None = None) -> tuple[np.ndarray, bool, np.ndarray]:
    """The control-rate array `cfg` exports for the source-rate trajectory q (T,n) at `fps`
    (`control.control_trajectory_checked`: resample, contact repair, and the torque and ZMP
    retiming when `cfg.dynamics_limits`), whether MuJoCo found every sample of it clear, and each
    sample's time (s) on the source's timeline. `kinematic`:
    q's control-rate array under `without_dynamics_limits(cfg)`, when a solve already made it."""
    return control_trajectory_checked(robot, q, fps, cfg.control_rate_hz, cfg.contact_repair,
                                      DynamicsLimits.from_config(cfg), kinematic=kinematic)


def control_counts(robot: Robot, q_control: np.ndarray, rate: float, clear: bool) -> dict[str, float]:
    """`control_*` metrics: `validation_counts` of a control-rate array (`clear`: MuJoCo already
    found every sample clear, so its contacts are not counted again)."""
    return {f"control_{k}": v for k, v in validation_counts(
        robot, q_control, rate, np.zeros(len(q_control), np.int64) if clear else None).items()}
