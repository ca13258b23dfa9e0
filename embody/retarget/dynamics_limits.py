"""Torque and balance limits of the exported control-rate trajectory, owned by its timing.

A kinematically valid trajectory can still ask a wrist motor for three times its torque, or
accelerate the arms hard enough to push the standing robot's ZMP out of its feet. The kinematic
chain (resample, joint box, velocity clamp, contact bridges and pushes) already gives a path
inside the joint box and the velocity limits whose samples keep every counted pair the export's
gap apart; what is left over is a matter of speed. Along a fixed path p(u), the joint torque
minus its static part (gravity, dry friction), the PD's velocity-lag share (kd·|q̈|/rate) and
the cart-table ZMP's distance from the CoM's projection all scale with the square of the speed
u̇, the joint velocities with u̇ itself. So this module keeps the path and retimes it
(path-velocity decomposition, as in time-optimal path parameterisation): the motion is slowed
down locally, only where a sample fails, by just enough. Sign location, handshape and contacts
stay those of the path; what the sign pays is time, reported per sequence as the largest local
slowdown (`time_stretch_max`) and the duration's growth (`duration_ratio`).

The path is the natural cubic spline through the input samples, knot u = sample index (the
spline the export's q̇ and feed-forward come from: `dynamics.spline_derivatives`). A stretch
profile f(u) ≥ 1 (linear between knots) sets dt/du = f/rate; the output samples are the path
at the retimed u(t_k), t_k = k / rate, and `source_time` = u(t_k) / rate is each output sample's
time on the input's timeline (what every comparison with the human reads). f = 1 everywhere
returns the input itself. Each connected stretched region adds a whole number of control
periods, so every sample outside the regions is an input sample exactly, and its MuJoCo verdict
carries over.

What is refused is the validation's and the physics replay's own definition
(`_Problem.failing_joints`): a joint whose exported feed-forward (rigid-body torque plus the dry
friction at the spline's slope) plus the PD lag share passes its effort limit; a cart-table ZMP
(`robot.dynamics.zmp`) closer than `zmp_margin` to the feet's edge; a velocity step past the
limit. Around each refused sample the stretch is raised by the factor that brings its dynamic
part back inside `torque_fraction` of the limit (the ZMP inside its margin), √(dynamic need /
room), the room being the limit less the static part at that pose; the raised need is widened
and smoothed (a Hann window: the stretch's own ü adds little acceleration), and the loop
re-evaluates the retimed array until nothing is refused (`ITERATIONS` at most). A pose whose
static part alone is over (gravity and friction past the limit, the CoM's projection outside
the margin) is a robot limit no timing fixes: it is counted (`Retimed.static_infeasible`) and
logged, and its sample stays refused. Between input samples the path is the spline, which MuJoCo
checks on the new samples (`near_contacts` at the export's gap); a touching one is pushed clear
by the contact repair's least-weighted push (`control._Separator.frame`), and the push is added
to the path itself, as a displacement of the spline over the source's time (ramped down over a
few knots and smoothed, so its acceleration falls with the stretch as the path's own does);
the pushed path is retimed again from the stretch reached (`CONTACT_ROUNDS`). Where the hands
pass through each other between two samples (synth seq 15: a wrist 45 mm inside the other hand)
the outcome is chaotic in the push's shape, so a few ramp widths are tried (`PUSH_RAMPS`);
where none leaves every sample clear, the input is kept.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import maximum_filter1d

from embody.config.ik import IKConfig
from embody.retarget.limits import EXPORT_GAP
from embody.robot import Robot
from embody.robot.contacts import near_contacts
from embody.robot.dynamics import (FRICTION_SPEED, GRAVITY, center_of_mass, derivatives, dof_adr,
                                   effort_limits, inverse_dynamics, leg_joints, spline_derivatives,
                                   stance_pose, standing_q, support_polygon)

log = logging.getLogger(__name__)

#: Retime-and-evaluate rounds at most.
ITERATIONS = 12
#: The stretch a round aims at is this far inside the bound (torque: × `torque_fraction` of the
#: limit; ZMP: this much (m) more than the margin), so that the loop converges from inside.
INNER = 0.97
ZMP_INNER = 0.003
INNER_VELOCITY = 0.99
#: Largest factor by which one round raises the stretch at a sample: the √ estimate holds for
#: the path's own acceleration; the stretch's own ü (p′·ü) is not in it.
ROUND_CAP = 3.0
#: Largest stretch (× slower) anywhere: beyond it the sample is left refused (a pose whose
#: static part alone is over never passes, whatever the timing).
STRETCH_MAX = 20.0
#: Knots on each side of a refused sample whose need is raised (the spline's acceleration at a
#: sample is set by its neighbours), and the half-width (knots) of the Hann window that smooths
#: the need into the stretch.
REACH = 2
SMOOTH = 4
#: Sub-steps per knot interval of the time map's numeric inverse.
SUBSTEPS = 16


@dataclass(frozen=True)
class DynamicsLimits:
    """What the exported array must honour: `torque_fraction` of each effort limit and `zmp_margin`
    (m) inside the standing robot's feet."""

    torque_fraction: float = 0.9
    zmp_margin: float = 0.02

    @classmethod
    def from_config(cls, cfg: Any) -> "DynamicsLimits | None":
        """From an `IKConfig`; None when `dynamics_limits` is off."""
        if not cfg.dynamics_limits:
            return None
        return cls(float(cfg.torque_limit_fraction), float(cfg.zmp_margin))


#: The `ik` section's defaults (`torque_limit_fraction`, `zmp_margin`).
DEFAULT_LIMITS = DynamicsLimits(IKConfig().torque_limit_fraction, IKConfig().zmp_margin)


def _velocity_lag(robot: Robot) -> np.ndarray:
    """Per joint (n,) the torque per unit acceleration (N·m·s²/rad) the motor's damping adds
    while its velocity lags one control period behind an accelerating reference: kd / rate.
    Why: a command is held for a period, so at the next one the joint's velocity trails the
    reference's by q̈ / rate, and the PD asks kd · q̈ / rate on top of the feed-forward (a G1
    wrist at 200 rad/s²: 1.2 N·m of its 5). Zero where the robot has no `actuation`."""
    try:
        from embody.physics.actuation import actuation
        act = actuation(robot)
    except Exception:  # noqa: BLE001 (a robot without gains: no lag to allow for)
        return np.zeros(robot.n_joints)
    return act.kd / act.rate_hz


class _Problem:
    """The robot's dynamics and balance at the control rate: evaluation of an array, what is
    refused in it, and the stretch each refused sample needs."""

    def __init__(self, robot: Robot, rate: float, limits: DynamicsLimits, velocity_margin: float = 0.0) -> None:
        self.robot, self.dt, self.limits = robot, 1.0 / rate, limits
        self.dof = dof_adr(robot)
        self.effort = effort_limits(robot)
        self.limited = np.isfinite(self.effort)
        # the dry friction, whatever its sign at a reversal: |rigid-body torque| + friction is held
        self.friction = robot.model.dof_frictionloss[self.dof]
        self.lag = _velocity_lag(robot)
        self.vstep = robot.velocity_limits * (1.0 - velocity_margin) * self.dt
        self.legs = leg_joints(robot)
        stand = robot.tpose.copy()
        stand[self.legs] = stance_pose(robot)[self.legs]
        self.polygon, self.floor = support_polygon(robot, stand)
        a, b = self.polygon, np.roll(self.polygon, -1, axis=0)
        e = b - a
        self.corner = a
        self.inward = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1)[:, None]

    def _edges(self, point: np.ndarray) -> np.ndarray:
        """(T,E) signed distances (m) of points (T,2) inside each edge of the support polygon."""
        return ((point[:, None, :] - self.corner[None]) * self.inward[None]).sum(-1)

    def evaluate(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Spline velocities and accelerations, rigid-body torques (T,n), gravity torques (T,n),
        the CoM (T,3), the cart-table ZMP's (T,E) and the CoM projection's (T,E) edge margins."""
        qd, qdd = spline_derivatives(x, self.dt)
        tau = inverse_dynamics(self.robot, x, self.dt, qd, qdd, friction=False)
        still = np.zeros_like(x)
        gravity = inverse_dynamics(self.robot, x, self.dt, still, still, friction=False)
        com = center_of_mass(self.robot, standing_q(self.robot, x))
        # `dynamics.zmp`'s cart-table ZMP, its support polygon computed once
        _, cdd = derivatives(com, self.dt)
        lever = (com[:, 2] - self.floor) / (cdd[:, 2] + GRAVITY)
        point = com[:, :2] - lever[:, None] * cdd[:, :2]
        return {"x": x, "qd": qd, "qdd": qdd, "tau": tau, "gravity": gravity, "com": com,
                "edge": self._edges(point), "edge_static": self._edges(com[:, :2])}

    def failing_joints(self, ev: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the validation and the physics replay refuse, per sample: (T,n) joints whose
        exported feed-forward (rigid-body torque plus the dry friction at the spline's slope,
        `dynamics.inverse_dynamics`) plus the PD's lag share (`_velocity_lag`) passes the effort
        limit itself, (T,) ZMP closer than `zmp_margin` to the feet's edge, (T,) a velocity step
        past the limit."""
        ff = ev["tau"] + self.friction * np.tanh(ev["qd"] / FRICTION_SPEED)
        tau = (np.abs(ff) + self.lag * np.abs(ev["qdd"]) > self.effort * (1.0 + 1e-9)) & self.limited
        zmp_ = (ev["edge"] < self.limits.zmp_margin).any(1)
        vel = np.zeros(len(tau), dtype=bool)
        v = (np.abs(np.diff(ev["x"], axis=0)) > self.vstep * (1.0 + 1e-9)).any(1)
        vel[1:] |= v
        vel[:-1] |= v
        return tau, zmp_, vel

    def failing(self, ev: dict[str, np.ndarray]) -> np.ndarray:
        """(T,) bool: samples the validation or the replay refuses (`failing_joints`)."""
        tau, zmp_, vel = self.failing_joints(ev)
        return tau.any(1) | zmp_ | vel

    def slowdown(self, ev: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(T,) the factor (≥ 1) by which each sample's motion must slow down for its dynamic
        part to fit the room its static part leaves (torque: `INNER` × `torque_fraction` of the
        limit, or the limit itself where the static part leaves no room under the fraction; ZMP:
        `ZMP_INNER` past the margin; velocity: `INNER_VELOCITY` of the limit), and (T,) bool the
        samples whose static part alone is over (no timing passes them)."""
        # torque: |g| + friction + (|τ − g| + lag·|q̈|)/k² within the bound
        dynamic = np.abs(ev["tau"] - ev["gravity"]) + self.lag * np.abs(ev["qdd"])
        static = np.abs(ev["gravity"]) + self.friction
        bound = INNER * self.limits.torque_fraction * self.effort
        room = np.where(bound - static > 0, bound - static, INNER * self.effort - static)
        with np.errstate(divide="ignore", invalid="ignore"):
            need_tau = np.where(self.limited & (room > 0), dynamic / room, np.where(self.limited, np.inf, 0.0))
        need = need_tau.max(1, initial=0.0)
        stuck = ~np.isfinite(need)
        # ZMP: edge(com) + (edge(zmp) − edge(com))/k² past the margin, per edge
        target = self.limits.zmp_margin + ZMP_INNER
        slack = ev["edge_static"] - target
        shift = ev["edge"] - ev["edge_static"]
        with np.errstate(divide="ignore", invalid="ignore"):
            need_zmp = np.where(ev["edge"] < target, np.where(slack > 0, -shift / slack, np.inf), 0.0)
        need_zmp = need_zmp.max(1)
        stuck |= ~np.isfinite(need_zmp)
        need = np.maximum(need, need_zmp)
        k = np.sqrt(np.maximum(need, 1.0))
        # velocity: the step into and out of each sample within the limit
        step = (np.abs(np.diff(ev["x"], axis=0)) / (INNER_VELOCITY * self.vstep)).max(1)
        kv = np.ones(len(k))
        kv[1:] = np.maximum(kv[1:], step)
        kv[:-1] = np.maximum(kv[:-1], step)
        return np.maximum(k, kv), stuck


@dataclass
class Retimed:
    """The retimed control-rate array and what its timing cost."""

    #: (N,n) the samples at the control rate.
    q: np.ndarray
    #: (N,) each sample's time (s) on the input's timeline (uniform k / rate where not retimed).
    source_time: np.ndarray
    #: Every limit holds on `q` (nothing refused).
    ok: bool
    #: Samples whose static part (gravity and friction, the CoM's projection) alone is refused.
    static_infeasible: int = 0
    #: New samples MuJoCo found touching on the spline between input samples, pushed clear.
    contact_samples: int = 0


def uniform_time(n: int, rate: float) -> np.ndarray:
    """(n,) the source times of a control-rate array that was not retimed: k / rate."""
    return np.arange(n, dtype=np.float64) / rate


def time_stretch(source_time: np.ndarray, rate: float) -> float:
    """The largest local slowdown of a retimed array: max over its periods of the control
    period over the source time it covers (1: not slowed anywhere)."""
    st = np.asarray(source_time, dtype=np.float64)
    if len(st) < 2:
        return 1.0
    return float((1.0 / rate) / max(float(np.diff(st).min()), 1e-12))


def duration_ratio(source_time: np.ndarray, rate: float) -> float:
    """The retimed array's duration over the source's ((N−1)/rate over its last source time)."""
    st = np.asarray(source_time, dtype=np.float64)
    if len(st) < 2 or st[-1] <= 0:
        return 1.0
    return float((len(st) - 1) / rate / st[-1])


def _hann(half: int) -> np.ndarray:
    w = np.hanning(2 * half + 3)[1:-1]
    return w / w.sum()


def _smooth(a: np.ndarray, half: int) -> np.ndarray:
    """a (T,) or (T,n) convolved along its first axis with the Hann window of half-width `half`,
    zero outside, the same length whatever T (`np.convolve`'s "same" is not, under the window)."""
    kernel = _hann(half)
    flat = a.reshape(len(a), -1)
    out = np.stack([np.convolve(c, kernel, mode="full")[half: half + len(a)] for c in flat.T], axis=1)
    return out.reshape(a.shape)


def _stretch(need: np.ndarray) -> np.ndarray:
    """(S,) the stretch at the knots from the per-knot need: widened (max filter) and smoothed
    (Hann) so that its full value covers every needing knot, each connected stretched region
    then scaled to add a whole number of control periods (`_regions`)."""
    wide = maximum_filter1d(need - 1.0, size=2 * SMOOTH + 1, mode="constant")
    f = 1.0 + _smooth(wide, SMOOTH)
    f[np.abs(f - 1.0) < 1e-12] = 1.0
    for a, b in _regions(f):
        seg = f[a: b + 1] - 1.0
        extra = float(0.5 * (seg[:-1] + seg[1:]).sum())  # ∫(f − 1) du, f linear between knots
        if extra > 0:
            f[a: b + 1] = 1.0 + seg * (np.ceil(extra - 1e-9) / extra)
    return f


def _regions(f: np.ndarray) -> list[tuple[int, int]]:
    """[a, b] knot ranges of each connected stretched region (f > 1 strictly inside, 1 at a, b)."""
    on = f > 1.0
    edge = np.diff(np.r_[0, on.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)
    return [(max(int(s) - 1, 0), min(int(e), len(f) - 1)) for s, e in zip(starts, ends)]


def _time_map(f: np.ndarray) -> np.ndarray:
    """u (knots, float) of each output sample for the stretch f (S,) at the knots, f linear
    between them: t(u) = ∫₀ᵘ f, in control periods; output k at t = k."""
    s = len(f)
    sub = np.linspace(0.0, 1.0, SUBSTEPS + 1)[1:]
    fa, fb = f[:-1, None], f[1:, None]
    # t within each interval: fa·v + (fb − fa)·v²/2
    within = fa * sub[None] + (fb - fa) * sub[None] ** 2 / 2.0
    start = np.r_[0.0, np.cumsum(0.5 * (f[:-1] + f[1:]))]
    t_fine = np.r_[0.0, (start[:-1, None] + within).ravel()]
    u_fine = np.r_[0.0, (np.arange(s - 1)[:, None] + sub[None]).ravel()]
    n = int(round(start[-1])) + 1
    u = np.interp(np.arange(n, dtype=np.float64), t_fine, u_fine)
    u[np.abs(u - np.round(u)) < 1e-9] = np.round(u[np.abs(u - np.round(u)) < 1e-9])
    u[-1] = s - 1
    return u


#: Retime-then-clear rounds at most, per push shape: the samples a round's retiming puts between
#: input samples (and those a push moved) are checked by MuJoCo, the touching ones pushed clear,
#: the pushes added to the path, and the path retimed again.
CONTACT_ROUNDS = 8
#: Points of the push displacement's grid per knot (the displacement is linear between them).
PUSH_GRID = 16
#: Knots (the input's samples) over which a push ramps down to zero on each side of its touching
#: samples (a raised cosine), tried in turn until one clears every sample: a wide ramp keeps the
#: push's acceleration low, a narrower one leaves more of the clear path beyond as it was. Why a
#: ladder: where the hands pass close the outcome is chaotic in the shape (over the 24 default
#: G1 inputs, synth seq 15 clears with 3 knots only, seq 17 with 5 only; 2, 2.5 and 4 lose both;
#: tests/data's seq 0 excerpt clears with 1.5-2.5 and 4, not with 3 or 5).
PUSH_RAMPS = (3.0, 5.0, 2.0)
#: Half-width (knots) of the Hann window that smooths each round's pushes (the linear pieces
#: between a run's pushes would be kinks, whose acceleration no stretch brings down).
PUSH_SMOOTH = 0.5


class _Path:
    """The path the retiming plays: the natural cubic spline through the input samples (knot
    u = sample index) plus a displacement D(u), zero but where a contact push moved it, inside
    the joint box. Why a displacement of the path rather than of the retimed samples: each round
    then retimes the same u, so a sample's source time is its u / rate exactly, and a push is
    retimed from the input's own timing (pushing retimed samples, then re-splining and retiming
    those, compounds the stretch and the pushes round after round: synth seq 15 grew to 4.9×
    its samples over six rounds without clearing)."""

    def __init__(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
        self.q, self.lower, self.upper = q, lower, upper
        self.spline = CubicSpline(np.arange(len(q), dtype=np.float64), q, bc_type="natural")
        self.grid = np.linspace(0.0, len(q) - 1.0, (len(q) - 1) * PUSH_GRID + 1)
        self.d = np.zeros((len(self.grid), q.shape[1]))

    def displacement(self, u: np.ndarray) -> np.ndarray:
        """(N,n) D at the knots u (N,), linear between its grid points."""
        pos = np.clip(np.asarray(u, dtype=np.float64) * PUSH_GRID, 0.0, len(self.grid) - 1.0)
        i = np.minimum(np.floor(pos).astype(np.int64), len(self.grid) - 2)
        w = (pos - i)[:, None]
        return (1.0 - w) * self.d[i] + w * self.d[i + 1]

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """(N,n) the path at u (N,): an input sample exactly where u is whole and nothing pushed it."""
        x = self.spline(u)
        exact = u == np.round(u)
        x[exact] = self.q[u[exact].astype(np.int64)]
        if self.d.any():
            x = x + self.displacement(u)
        return np.clip(x, self.lower, self.upper)

    def moved(self, u: np.ndarray) -> np.ndarray:
        """(N,) bool: the samples at u (N,) that are not input samples (MuJoCo checks them)."""
        off = u != np.round(u)
        if self.d.any():
            off |= np.abs(self.displacement(u)).max(1) > 0
        return off

    def push(self, u: np.ndarray, delta: np.ndarray, ramp: float) -> None:
        """Add the pushes delta (K,n) found at the knots u (K,) to D: per run of touching samples
        (less than `ramp` knots apart) the pushes, linear between them, ramped down to zero over
        `ramp` knots on each side (a raised cosine), per joint the largest where two runs' ramps
        meet, smoothed (Hann, `PUSH_SMOOTH`)."""
        g = self.grid
        add = np.zeros_like(self.d)
        splits = np.flatnonzero(np.diff(u) >= ramp) + 1
        for run_u, run_d in zip(np.split(u, splits), np.split(delta, splits)):
            near = (g > run_u[0] - ramp) & (g < run_u[-1] + ramp)
            gn = g[near]
            held = np.stack([np.interp(gn, run_u, run_d[:, j]) for j in range(self.d.shape[1])], axis=1)
            out = np.maximum(run_u[0] - gn, gn - run_u[-1]).clip(0.0) / ramp
            held *= (0.5 * (1.0 + np.cos(np.pi * out)))[:, None]
            cur = add[near]
            add[near] = np.where(np.abs(held) > np.abs(cur), held, cur)
        self.d += _smooth(add, int(round(PUSH_SMOOTH * PUSH_GRID)))


def retime_dynamics(robot: Robot, q: np.ndarray, rate: float, limits: DynamicsLimits, *,
                    box_margin: float = 0.0, velocity_margin: float = 0.0) -> Retimed:
    """q (S,n) at `rate` Hz retimed (the path kept, the motion slowed down locally where a
    sample is refused) until every sample's torque and PD lag are within the effort limits, the
    standing robot's ZMP `limits.zmp_margin` inside its feet and every joint inside its velocity
    limit (× (1 − velocity_margin)), the samples kept inside the joint box (shrunk by
    `box_margin`) and MuJoCo-clear at the export's gap. An input with nothing refused comes back
    as is (the same values, uniform `source_time`).

    Each round retimes the path (`_retime`); the samples that are not input samples are checked
    by MuJoCo, the touching ones pushed clear (`_push_clear`) and the pushes added to the path
    (`_Path.push`), which the next round retimes again from the stretch the last one reached.
    A push shape (`PUSH_RAMPS`) that leaves a sample penetrating is given up for the next; where
    none clears, the input is kept."""
    q = np.array(q, dtype=np.float64)
    prob = _Problem(robot, rate, limits, velocity_margin)
    lower, upper = robot.lower + box_margin, robot.upper - box_margin
    pushed = 0
    for ramp in PUSH_RAMPS:
        x, u, ok, static, touching, n = _retime_clear(robot, prob, q, lower, upper, ramp)
        pushed += n
        if not touching.any() or not (near_contacts(robot, x[touching], 0.0) > 0).any():
            break
        log.debug("pushes ramped over %.1f knots left a sample penetrating", ramp)
    else:
        # no push shape cleared the retimed samples: never a contact for a torque, the input stands
        log.warning("the retimed samples' contacts could not all be pushed clear: the input is kept")
        return Retimed(q, uniform_time(len(q), rate), False, static, pushed)
    if static:
        log.warning("%d samples are over a limit at rest (gravity and friction, or the CoM's "
                    "projection): no timing passes them", static)
    return Retimed(x, u / rate, ok, static, pushed)


def _retime_clear(robot: Robot, prob: _Problem, q: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                  ramp: float) -> tuple[np.ndarray, np.ndarray, bool, int, np.ndarray, int]:
    """The contact rounds with pushes ramped over `ramp` knots: the samples, their knots u,
    whether nothing is refused, the samples over at rest, (N,) the samples still touching at
    the export's gap, and how many samples were pushed."""
    path = _Path(q, lower, upper)
    need = np.ones(len(q))
    pushed = 0
    for _round in range(CONTACT_ROUNDS + 1):
        x, u, ok, static, need = _retime(prob, path, need)
        new = np.flatnonzero(path.moved(u))
        touch = np.zeros(len(x), dtype=bool)
        touch[new] = near_contacts(robot, x[new], EXPORT_GAP) > 0
        log.debug("contact round %d: %d samples, %d new, %d touching", _round, len(x), len(new), int(touch.sum()))
        if not touch.any() or _round == CONTACT_ROUNDS:
            break
        rows = np.flatnonzero(touch)
        pushed += len(rows)
        path.push(u[rows], _push_clear(robot, x, rows, lower, upper), ramp)
    return x, u, ok, static, touch, pushed


def _retime(prob: _Problem, path: _Path, need: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, bool, int, np.ndarray]:
    """The path retimed until nothing is refused (`ITERATIONS` rounds at most), starting from
    the per-knot `need` (S,) (the stretch never falls below it): the samples, their knots u
    (input samples where u is whole and the path not pushed), whether nothing is refused, how
    many refused samples are over at rest, and the per-knot need reached. Nothing refused at
    the starting stretch: those samples (the input itself when nothing was needed or pushed)."""
    s = len(path.q)
    knots = np.arange(s, dtype=np.float64)
    need = need.copy()
    f = _stretch(need) if (need > 1.0).any() else np.ones(s)
    u = _time_map(f) if (f > 1.0).any() else knots
    x = path(u)
    if s < 3:
        return x, u, True, 0, need
    ev = prob.evaluate(x)
    bad = prob.failing(ev)
    for _round in range(ITERATIONS):
        if not bad.any():
            break
        k, stuck = prob.slowdown(ev)
        if not (bad & ~stuck).any():
            break
        # a sample whose static part alone is over is not slowed: no timing passes it
        k = np.where(bad & ~stuck, np.clip(k * 1.02, 1.05, ROUND_CAP), 1.0)
        raised = np.interp(u, knots, f) * k
        for offset in range(-REACH, REACH + 2):
            idx = np.clip(np.floor(u[bad]).astype(np.int64) + offset, 0, s - 1)
            np.maximum.at(need, idx, raised[bad])
        need = np.minimum(need, STRETCH_MAX)
        f = _stretch(need)
        u = _time_map(f)
        x = path(u)
        ev = prob.evaluate(x)
        bad = prob.failing(ev)
        log.debug("retime round %d: %d samples, stretch max %.2f, %d refused", _round, len(x), f.max(),
                  int(bad.sum()))
    static = int((bad & prob.slowdown(ev)[1]).sum()) if bad.any() else 0
    return x, u, not bad.any(), static, need


#: Trust radius (rad) of a contact push.
PUSH_TRUST = np.radians(10.0)


def _push_clear(robot: Robot, x: np.ndarray, rows: np.ndarray, lower: np.ndarray,
                upper: np.ndarray) -> np.ndarray:
    """(K,n) the pushes that clear the samples `rows` (K,) of x: the contact repair's least
    weighted push (`control._Separator.frame`, at the export's gap) within `PUSH_TRUST` of the
    sample, each started from the push of the touching sample before it in the same run (the
    run's samples pushed the same way round, rather than each its own way)."""
    from embody.retarget.control import _Separator
    sep = _Separator(robot, gap=EXPORT_GAP)  # pushed to the repair's own clearance
    delta = np.zeros((len(rows), x.shape[1]))
    for i, t in enumerate(rows):
        lo, hi = np.maximum(lower, x[t] - PUSH_TRUST), np.minimum(upper, x[t] + PUSH_TRUST)
        start = x[t] + delta[i - 1] if i and rows[i - 1] == t - 1 else x[t]
        delta[i] = sep.frame(np.clip(start, lo, hi), lo, hi) - x[t]
    return delta
