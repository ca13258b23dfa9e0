"""Collision-free joint trajectories at any rate: MuJoCo contact repair and the control-rate resample.

Interpolating between two collision-free frames is not collision-free when the hands pass within
millimetres of each other, and the sphere/hull proxies steering the IK are approximations. So the
last word is MuJoCo's: every sample of a written trajectory is checked with `mj_collision` (the
same counted pairs as `embody.robot.contacts`), and a sample with penetrating contacts is pushed
apart along the contact normals. Per contact i, with normal n_i (geom1 → geom2), depth d_i < 0 and
point Jacobians J1, J2 of the two bodies, the separation rate is a_i = n_iᵀ (J2 − J1); the
weighted least-norm step δ = W⁻¹Aᵀ(AW⁻¹Aᵀ + μI)⁻¹(clearance − d) is repeated until the sample is
clear (a damped Gauss-Newton on the contact distances). The correction is blended into the
neighbouring samples (a hat window, wide enough that its ramps use at most half of each joint's
velocity limit) so it does not create a velocity spike, then the trajectory is
clipped to the joint box and clamped to the velocity limits, and re-checked; a few passes.
The repair is local: every joint stays inside a trust radius of its input (`TRUST_DEG`, tried
smallest first; a step that would leave it holds those joints at the bound and solves the rest
again), so a touching sample gets the smallest push that clears it and the hat stays narrow.

`control_trajectory` is what the library exports: the source-rate trajectory resampled to the
control rate, repaired at every control sample, and kept a hair inside the joint box and the
velocity limits so that a float32 cast (BeyondMimic's reader) cannot push it over. Its repair
order: a bridge between a touching run's clear neighbours, pushes within 5-10°, then the
smaller change of a bridge over a wider window and a wider push.
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.retarget.dynamics_limits import DEFAULT_LIMITS, DynamicsLimits, retime_dynamics, uniform_time
from embody.retarget.limits import EXPORT_GAP, EXPORT_GAP_PUSH, clamp_velocity, resample, velocity_violations
from embody.robot import Robot
from embody.robot.contacts import collision_model, near_contacts

#: Clearance (m) a repaired sample gets between the geoms that penetrated.
CLEARANCE = 0.002
#: Repair passes before a trajectory is reported not clear. Each pass re-checks only the samples
#: the last one changed, so clean trajectories stop at the first; 12 left synth seq 15's 50 Hz
#: export with a fingertip 2.3 mm in the other wrist (export-invalid), 24 cleared it.
PASSES = 32
#: Passes a trust radius may run without a new fewest-touching count before it is given up for
#: the next (the ladder's last radius, whose result stands when none clears, runs all). Why: a
#: radius that cannot clear a sample stalls at the same count from its second pass
#: (tests/test_ik_tracking_preset.py's tight solve: 5°, 7.5° and 10° sat at 19-21 touching
#: samples for all 32 passes, 120 of the solve's 135 CPU-s), while over the 24 default inputs no
#: call that cleared went more than 11 passes without a new fewest count.
STALL_PASSES = 12
#: Margin (rad) kept inside the joint box, and relative margin under the velocity limits, in the
#: exported control-rate array: larger than float32 rounding (≤ 2.4e-7 rad below 4 rad).
BOX_MARGIN = 1e-6
VELOCITY_MARGIN = 1e-5
#: Cost of moving a joint class in the repair step (larger = moved less): arms move first,
#: fingers (the handshape carries meaning) and the waist only when needed.
WEIGHTS = {"arm": 1.0, "hand": 25.0, "waist": 25.0}
#: Trust radii (degrees, per joint, from the input sample) the repair is tried within, in turn;
#: None: the joint box only, the last resort that keeps every exported sample clear. Why: an
#: unbounded push from a deep, ambiguous contact (normals of interpenetrating meshes) can take a
#: large step, and the hat spreads it into neighbours that then touch and get pushed in turn: on
#: synth seq 17 (s9-ikwin run) three touching 50 Hz samples swung the arms by ~110° over 0.9 s,
#: where a 5° box cleared them. A radius that fails costs only its passes (chaotic: 15° can fail
#: where 10° and 20° clear, hence the ladder).
TRUST_DEG: tuple[float | None, ...] = (5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 40.0, None)
#: The radii (leading entries of TRUST_DEG) the export tries before its wider bridge.
SMALL = 3


class _Separator:
    """Per-sample contact repair on one robot (one MjData, reused). A counted pair closer than
    `gap` (m; 0: penetrating) is a contact, pushed to `clearance`."""

    def __init__(self, robot: Robot, clearance: float = CLEARANCE, gap: float = 0.0) -> None:
        self.robot, self.gap = robot, gap
        self.clearance = max(clearance, gap + EXPORT_GAP_PUSH) if gap else clearance
        self.model, self.counted = collision_model(robot, margin=gap)  # the counted pairs' only
        self.data = mujoco.MjData(self.model)
        jid = [self.model.joint(n).id for n in robot.joint_names]
        self.dof = self.model.jnt_dofadr[jid]
        hands = {j for side in robot.spec.hands for j in robot.hand_joint_names(side)}
        waist = set(robot.waist_joint_names)
        movable = [i for i, n in enumerate(robot.joint_names) if robot.ik_mask[i] or n in hands]
        self.movable = np.array(movable, dtype=np.int64)
        self.weight = np.array([WEIGHTS["waist"] if robot.joint_names[i] in waist else
                                WEIGHTS["hand"] if robot.joint_names[i] in hands else WEIGHTS["arm"]
                                for i in movable])
        self.jacp = np.zeros((3, self.model.nv))
        self.jac2 = np.zeros((3, self.model.nv))

    def contacts(self, q: np.ndarray, jacobians: bool = True) -> list[int]:
        """Indices (into data.contact) of counted contacts closer than `gap` at joint values q
        (`jacobians`: also prepare `mj_jac`, which needs `mj_comPos`)."""
        d = self.data
        d.qpos[:] = self.model.qpos0
        d.qpos[self.robot.qpos_adr] = q
        mujoco.mj_kinematics(self.model, d)
        if jacobians:
            mujoco.mj_comPos(self.model, d)
        mujoco.mj_collision(self.model, d)
        n = d.ncon
        if not n:
            return []
        geom = d.contact.geom[:n]
        hit = (d.contact.dist[:n] < self.gap) & self.counted[geom[:, 0], geom[:, 1]]
        return np.flatnonzero(hit).tolist()

    def frame(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray,
              iterations: int = 40) -> np.ndarray:
        """q moved (least weighted change) until MuJoCo reports no counted penetration."""
        q = q.copy()
        m, d = self.model, self.data
        cols = self.dof[self.movable]
        for _ in range(iterations):
            hits = self.contacts(q)
            if not hits:
                break
            rows, gap = [], []
            for i in hits:
                c = d.contact[i]
                n = c.frame[:3]
                b1, b2 = m.geom_bodyid[c.geom[0]], m.geom_bodyid[c.geom[1]]
                mujoco.mj_jac(m, d, self.jacp, None, c.pos, b1)
                mujoco.mj_jac(m, d, self.jac2, None, c.pos, b2)
                rows.append(n @ (self.jac2 - self.jacp)[:, cols])
                gap.append(self.clearance - c.dist)
            x = q[self.movable]
            step = self._step(np.array(rows), np.array(gap), lower[self.movable] - x, upper[self.movable] - x)
            step *= min(1.0, 0.15 / max(np.abs(step).max(), 1e-12))  # linearisation holds for small steps
            q[self.movable] = np.clip(x + step, lower[self.movable], upper[self.movable])
        return q

    def _step(self, a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The least weighted step with a·step = b inside [lo, hi] (lo ≤ 0 ≤ hi): the least-norm
        solve, with the joints it would push past a bound held there and the rest solved again
        (a few active-set rounds). Why: clipping the free solution alone drops the part of the
        correction the bounded joints carried, so inside a small trust box the Gauss-Newton
        crawls (or stalls) where the joints still free could have separated the sample."""
        free = np.ones(len(lo), dtype=bool)
        held = np.zeros(len(lo))
        step = held
        for _ in range(4):
            winv = np.where(free, 1.0 / self.weight, 0.0)
            aw = a * winv
            step = held + aw.T @ np.linalg.solve(aw @ a.T + 1e-6 * np.eye(len(b)), b - a @ held)
            out = free & ((step < lo) | (step > hi))
            if not out.any():
                break
            held = np.where(out, np.clip(step, lo, hi), held)
            free &= ~out
        return np.clip(step, lo, hi)


def _spread(delta: np.ndarray, half_width: int) -> np.ndarray:
    """Blend per-sample corrections into ±half_width neighbours with a hat window (per joint the
    largest weighted correction wins, so overlapping windows never add up)."""
    out = delta.copy()
    t = len(delta)
    for k in range(1, min(half_width, t - 1) + 1):
        w = 1.0 - k / (half_width + 1)
        for src, dst in ((slice(0, t - k), slice(k, t)), (slice(k, t), slice(0, t - k))):
            cand, cur = w * delta[src], out[dst]
            out[dst] = np.where(np.abs(cand) > np.abs(cur), cand, cur)
    return out


#: Longest run of contact frames (source rate) `bridge_contacts` replaces by interpolation.
BRIDGE_FRAMES = 3
#: How far (s) the export's wider bridge may reach out on each side of a contact run, when no
#: small push clears it: a few control samples.
BRIDGE_GROW_S = 0.1


def bridge_contacts(robot: Robot, q: np.ndarray, max_run: int = BRIDGE_FRAMES,
                    fps: float | None = None, bad: np.ndarray | None = None,
                    grow: int = 0) -> np.ndarray:
    """`bridge_contacts_checked`'s trajectory."""
    return bridge_contacts_checked(robot, q, max_run, fps, bad, grow)[0]


def bridge_contacts_checked(robot: Robot, q: np.ndarray, max_run: int = BRIDGE_FRAMES,
                            fps: float | None = None, bad: np.ndarray | None = None,
                            grow: int = 0, gap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """q (T,n) with each short run (≤ `max_run` frames) of MuJoCo contact frames between two clear
    frames replaced by a clear one between those neighbours: the straight line, the line pushed
    clear (`_Separator.frame`), or the neighbours held; the first that MuJoCo finds clear on
    every frame and, with `fps`, that keeps the velocity limits into, through and out of the run
    (else the run is left to `separate`: a bridge the clamp then bends would only come back as
    a contact). Why: a jittering target can
    flip a solve through a contact on isolated frames (synth seq 6: palms 35 mm inside each
    other on frames 121 and 123, 120 and 122 clear); pushing such a frame apart along MuJoCo's
    normals moved the arms by up to 76° over ±0.5 s, while its clear neighbours already bound
    a local, collision-free answer. `bad` (T,) bool: MuJoCo's verdict on q when the caller
    already has it (the IK's contact phase checks the same q just before). `grow`: when no
    candidate between the run's own neighbours works, the bridge is retried between clear samples
    up to `grow` further out on each side (a longer path: more time for the same change, so a
    velocity-feasible one is likelier; the samples in between are replaced too, and must be clear).
    Also MuJoCo's verdict (T,) bool on the returned q: the input's, with every bridged sample
    clear (each was checked), so the repair after it need not check the clear samples again.
    `gap` (m): a counted pair closer than it counts as touching (0: penetrating)."""
    q = np.array(q, dtype=np.float64)
    sep = _Separator(robot, gap=gap)
    if bad is None:
        bad = np.array([bool(sep.contacts(x, jacobians=False)) for x in q])
    bad = np.asarray(bad, dtype=bool)
    verdict = bad.copy()
    t, n = 0, len(q)
    while t < n:
        if not bad[t]:
            t += 1
            continue
        end = t
        while end < n and bad[end]:
            end += 1
        if t > 0 and end < n and end - t <= max_run:
            for g in range(grow + 1):
                a, b = t - 1 - g, end + g  # the clear samples the bridge joins
                if a < 0 or b >= n or bad[a] or bad[b]:
                    continue
                if _bridge(sep, robot, q, a, b, fps):
                    verdict[a + 1: b] = False
                    break
        t = end
    return q, verdict


def _bridge(sep: _Separator, robot: Robot, q: np.ndarray, a: int, b: int, fps: float | None) -> bool:
    """Replace q[a+1:b] in place by the first clear candidate joining q[a] and q[b] (straight,
    pushed clear, held) that, with `fps`, keeps the velocity limits; whether one was found. The
    push stays within the neighbours' range ± the smallest trust radius: a local answer."""
    w = (np.arange(a + 1, b) - a)[:, None] / float(b - a)
    line = (1.0 - w) * q[a] + w * q[b]
    r = np.radians(TRUST_DEG[0])
    lo = np.maximum(robot.lower, np.minimum(q[a], q[b]) - r)
    hi = np.minimum(robot.upper, np.maximum(q[a], q[b]) + r)
    for cand in (line, np.stack([sep.frame(x, lo, hi) for x in line]),
                 np.where(w < 0.5, q[a], q[b])):  # straight, pushed, held
        path = np.concatenate([q[a: a + 1], cand, q[b: b + 1]])
        if fps is not None and velocity_violations(path, robot.velocity_limits, fps):
            continue
        if not any(sep.contacts(x, jacobians=False) for x in cand):
            q[a + 1: b] = cand
            return True
    return False


def separate(robot: Robot, q: np.ndarray, fps: float, *, passes: int = PASSES, blend_s: float = 0.1,
             box_margin: float = 0.0, velocity_margin: float = 0.0,
             clearance: float = CLEARANCE, enforce_velocity: bool = True,
             trust_deg: tuple[float | None, ...] = TRUST_DEG) -> np.ndarray:
    """q (T,n) with every sample's penetrating self-contacts removed (MuJoCo's verdict), inside
    the joint box (shrunk by `box_margin`) and the velocity limits (× (1 − velocity_margin))."""
    return separate_checked(robot, q, fps, passes=passes, blend_s=blend_s, box_margin=box_margin,
                            velocity_margin=velocity_margin, clearance=clearance,
                            enforce_velocity=enforce_velocity, trust_deg=trust_deg)[0]


def separate_checked(robot: Robot, q: np.ndarray, fps: float, *, passes: int = PASSES, blend_s: float = 0.1,
                     box_margin: float = 0.0, velocity_margin: float = 0.0, clearance: float = CLEARANCE,
                     enforce_velocity: bool = True,
                     trust_deg: tuple[float | None, ...] = TRUST_DEG,
                     touching: np.ndarray | None = None, gap: float = 0.0) -> tuple[np.ndarray, bool]:
    """`separate`, and whether MuJoCo checked every returned sample clear (False only when no
    trust radius cleared it: each ran out of passes or stalled, `STALL_PASSES`): a caller then
    need not run the same collision check again. The repair is tried inside each trust radius of
    `trust_deg` in turn (no joint of any sample leaves ± that many degrees of its input value;
    None: unbounded) and the first that
    clears every sample wins: the smallest correction that works, never a wide swing when a
    small one exists. `touching` (T,) bool: MuJoCo's verdict on q when the caller has it (the
    bridge's); the samples it finds clear are not checked again on the first pass. `gap` (m): a
    counted pair closer than it is a contact (0: penetrating), pushed past it."""
    q = np.array(q, dtype=np.float64)
    out, clear = q, False
    sep = _Separator(robot, clearance, gap)
    check = np.ones(len(q), dtype=bool) if touching is None else np.array(touching, dtype=bool)
    for i, radius in enumerate(trust_deg):
        # the last radius is the answer when none clears: it runs its whole budget
        stall = STALL_PASSES if i < len(trust_deg) - 1 else passes
        out, clear, check = _separate_within(sep, q, fps, None if radius is None else np.radians(radius),
                                             passes, blend_s, box_margin, velocity_margin,
                                             enforce_velocity, check, stall)
        if clear:
            break
    return out, clear


def _separate_within(sep: _Separator, q: np.ndarray, fps: float, radius: float | None, passes: int,
                     blend_s: float, box_margin: float, velocity_margin: float,
                     enforce_velocity: bool, check: np.ndarray,
                     stall: int = STALL_PASSES) -> tuple[np.ndarray, bool, np.ndarray]:
    """The repair passes with every joint kept within `radius` (rad) of q (None: the joint box
    only), given up after `stall` passes without a new fewest-touching count; the result,
    whether it is clear, and the samples of q whose verdict the caller does not know (`check`
    in: the samples to check on the first pass; out: the first pass's touching
    samples, all that a retry at another radius must look at again)."""
    robot = sep.robot
    lower, upper = robot.lower + box_margin, robot.upper - box_margin
    lo = np.broadcast_to(lower, q.shape) if radius is None else np.maximum(lower, q - radius)
    hi = np.broadcast_to(upper, q.shape) if radius is None else np.minimum(upper, q + radius)
    vmax = robot.velocity_limits * (1.0 - velocity_margin)
    half = max(int(round(blend_s * fps)), 0)
    first = None
    best, since = len(q) + 1, 0
    for _ in range(passes):
        bad = [t for t in np.flatnonzero(check) if sep.contacts(q[t], jacobians=False)]
        if first is None:
            first = np.zeros(len(q), dtype=bool)
            first[bad] = True
        if not bad:
            return q, True, first
        # every sample outside `check` was found clear before and is unchanged: bad is the count
        best, since = (len(bad), 0) if len(bad) < best else (best, since + 1)
        if since >= stall:
            return q, False, first
        delta = np.zeros_like(q)
        local = q.copy()
        for t in bad:
            fixed, tried = _within_velocity(sep, local, t, lo[t], hi[t], vmax / fps) \
                if enforce_velocity else (None, None)
            if fixed is not None:  # cleared where it stands: no hat, the neighbours kept
                local[t] = fixed
            elif tried is not None and all(np.array_equal(u, v) for u, v in zip(tried[:3], (q[t], lo[t], hi[t]))):
                delta[t] = tried[3] - q[t]  # the neighbours left the box as it was: that push again
            else:
                delta[t] = sep.frame(q[t], lo[t], hi[t]) - q[t]
        # a wide enough hat that its ramps take at most half of each joint's velocity budget
        with np.errstate(divide="ignore", invalid="ignore"):
            ramp = np.nan_to_num(np.abs(delta) / (vmax / fps), nan=0.0, posinf=0.0)
        width = max(half, int(np.ceil(2.0 * ramp.max())))
        new = np.clip(local + _spread(delta, width), lo, hi)
        if enforce_velocity:
            new = clamp_velocity(new, vmax, fps)
        check = np.any(new != q, axis=1)
        check[bad] = True  # a repair undone by the clip/clamp leaves its verdict unknown
        q = new
    return q, False, first


def _within_velocity(sep: _Separator, q: np.ndarray, t: int, lo: np.ndarray, hi: np.ndarray,
                     step: np.ndarray) -> tuple[np.ndarray | None, tuple | None]:
    """Sample t of q pushed clear inside the box its neighbours' velocity limits leave it
    (`step`: the largest change per sample), or None when that box has no clear pose. Why: on
    a run where a joint already moves at its velocity limit (synth seq 15's wrists at 50 Hz),
    any hat changes the run's slope and the velocity clamp undoes it pass after pass; a
    correction that stays inside the neighbours' reach needs no hat at all. Also the push it
    tried (start, box low, box high, result; None when the box was empty): where the box is
    the caller's own and the start q[t], the caller's push is that one (not computed twice)."""
    a, b = lo.copy(), hi.copy()
    for n in (t - 1, t + 1):
        if 0 <= n < len(q):
            a = np.maximum(a, q[n] - step * (1.0 - 1e-6))
            b = np.minimum(b, q[n] + step * (1.0 - 1e-6))
    if (a > b).any():
        return None, None
    start = np.clip(q[t], a, b)
    x = sep.frame(start, a, b)
    return (None if sep.contacts(x, jacobians=False) else x), (start, a, b, x)


def control_trajectory(robot: Robot, q: np.ndarray, fps: float, rate: float,
                       repair: bool = True, limits: DynamicsLimits | None = DEFAULT_LIMITS) -> np.ndarray:
    """The exported control-rate trajectory (float64): q resampled to `rate` Hz, then every
    sample made collision-free and kept strictly inside the joint and velocity limits, and
    (`limits`, the `ik` defaults unless given; None: the kinematic limits only) retimed where
    it asks more than the motors' torque or the standing robot's balance allow
    (`control_trajectory_checked` also gives each sample's source time)."""
    return control_trajectory_checked(robot, q, fps, rate, repair, limits)[0]


def control_trajectory_checked(robot: Robot, q: np.ndarray, fps: float, rate: float,
                               repair: bool = True, limits: DynamicsLimits | None = DEFAULT_LIMITS,
                               kinematic: np.ndarray | None = None) -> tuple[np.ndarray, bool, np.ndarray]:
    """`control_trajectory`, whether MuJoCo found every returned sample clear, and each
    sample's time (s) on the source's timeline (`dynamics_limits.Retimed.source_time`: k / rate
    where the array was not retimed). `kinematic`: this very call's array with `limits=None`
    (same q, fps, rate and repair), when the caller already has it (a solve without the
    dynamics limits made it): its resample and contact repair are not run again, only MuJoCo's
    verdict on its samples (the contact repair of a critic's chosen round cost as much as its
    solve)."""
    if kinematic is None:
        out, clear = _kinematic_control(robot, q, fps, rate, repair)
    else:
        out = np.array(kinematic, dtype=np.float64)
        clear = not (near_contacts(robot, out, EXPORT_GAP) > 0).any()
    if limits is None:
        return out, clear, uniform_time(len(out), rate)
    # the retiming keeps the path: every input sample it keeps is itself, and the new samples
    # between them it checks (and clears) at the same gap, so MuJoCo's verdict carries over
    timed = retime_dynamics(robot, out, rate, limits, box_margin=BOX_MARGIN, velocity_margin=VELOCITY_MARGIN)
    return timed.q, clear, timed.source_time


def _kinematic_control(robot: Robot, q: np.ndarray, fps: float, rate: float,
                       repair: bool) -> tuple[np.ndarray, bool]:
    """The control-rate trajectory inside the joint box, the velocity limits and (`repair`)
    MuJoCo's contacts, and whether MuJoCo found every sample clear."""
    qc = resample(np.asarray(q, dtype=np.float64), fps, rate)
    qc = np.clip(qc, robot.lower + BOX_MARGIN, robot.upper - BOX_MARGIN)
    qc = clamp_velocity(qc, robot.velocity_limits * (1.0 - VELOCITY_MARGIN), rate)
    if not repair:
        return qc, False
    # interpolated samples that touch between clear ones: bridged locally first, as at the source
    # rate (the repair alone moved synth seqs 15 and 17's exported arms by 89-101°)
    run = int(np.ceil(BRIDGE_FRAMES * rate / fps))
    qc, touching = bridge_contacts_checked(robot, qc, max_run=run, fps=rate, gap=EXPORT_GAP)
    kw = {"box_margin": BOX_MARGIN, "velocity_margin": VELOCITY_MARGIN, "gap": EXPORT_GAP}
    out, clear = separate_checked(robot, qc, rate, trust_deg=TRUST_DEG[:SMALL], touching=touching, **kw)
    if clear:
        return out, clear
    # no small push clears it: a bridge over a wider window, or a wider push, whichever changes
    # the resample less (the bridge is a straight path between clear samples, but it may still
    # move more than a 15° push would)
    out, clear = separate_checked(robot, qc, rate, trust_deg=TRUST_DEG[SMALL:], touching=touching, **kw)
    wide, wide_touching = bridge_contacts_checked(robot, qc, max_run=run, fps=rate, bad=touching,
                                                  grow=int(np.ceil(BRIDGE_GROW_S * rate)), gap=EXPORT_GAP)
    if not np.array_equal(wide, qc):
        bridged, bridged_clear = separate_checked(robot, wide, rate, touching=wide_touching, **kw)
        if bridged_clear and (not clear or np.abs(bridged - qc).max() <= np.abs(out - qc).max()):
            return bridged, bridged_clear
    return out, clear
