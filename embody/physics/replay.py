"""Replay low-level commands in MuJoCo at the robot's control rate.

Each control step holds one command per motor (zero-order hold, as a robot stack sends them):
the reference q and q̇ of the 50 Hz samples interpolated by a cubic Hermite spline (the samples'
q and q̇) at the step's time, quantised to the joint group's command rate, and the feed-forward
torque interpolated linearly. The motor applies

    τ = clip(kp (q_ref − q) + kd (q̇_ref − q̇) + τ_ff, ±effort limit)

evaluated by MuJoCo every physics step (an affine position actuator whose control folds the
feed-forward in: ctrl = q_ref + (τ_ff + kd q̇_ref) / kp, force range = the effort limit), with
the physics timestep = 1 / control rate and the implicit-in-velocity integrator. The whole
rollout runs inside MuJoCo (`mujoco.rollout`): no Python per step.

Two setups, each a reduced model built once per robot:
- fixed base: free joint and leg joints removed (pelvis welded, legs at 0, which is the stance
  of both robots here); contacts off: self-contacts are counted on the simulated motion.
- standing: free base on a floor plane, finger joints removed (welded open), contacts only
  between the feet and the floor (elliptic friction, `FOOT_IMPRATIO`, a 2-step contact time
  constant); the legs under the stance controller: stiff PD toward the stance plus the
  feed-forward of the feet carrying the moving body (`stance_torques`).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import rollout
from scipy.interpolate import CubicHermiteSpline

from embody.physics.actuation import actuation
from embody.physics.commands import Commands
from embody.robot.dynamics import leg_joints, stance_pose, support_polygon
from embody.robot.model import Robot


@dataclass(frozen=True)
class ReplayModel:
    """A compiled replay model and where the robot's joints sit in it."""

    model: mujoco.MjModel
    #: Robot joint index (robot.joint_names) of each actuator, in actuator order.
    joints: np.ndarray
    #: qpos / qvel addresses of each actuator's joint.
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    #: Each actuator's gains and effort limit.
    kp: np.ndarray
    kd: np.ndarray
    limit: np.ndarray


def _compiled(robot: Robot, drop: np.ndarray, fixed: bool, floor: float | None,
              kp: np.ndarray, kd: np.ndarray, limit: np.ndarray) -> mujoco.MjModel:
    """`_edit`'s model, kept as MJB in embody's cache (compiling the G1's meshes takes ~1 s), keyed
    by the MJCF's own key (`compiled_model`) and every edit."""
    import hashlib

    from embody.robot.compiled import cached_model, model_key
    blob = repr((_EDIT_VERSION, model_key(robot.mjcf_path), robot.joint_names, drop.tolist(), fixed,
                 floor, kp.tolist(), kd.tolist(), limit.tolist()))
    return cached_model(f"replay-{hashlib.sha256(blob.encode()).hexdigest()[:20]}",
                        lambda: _edit(robot, drop, fixed, floor, kp, kd, limit))


#: Bump when `_edit` builds another model from the same inputs.
_EDIT_VERSION = 1


def _edit(robot: Robot, drop: np.ndarray, fixed: bool, floor: float | None,
          kp: np.ndarray, kd: np.ndarray, limit: np.ndarray) -> mujoco.MjModel:
    """The robot's MJCF with the free joint (`fixed`) and the `drop` joints removed, its
    actuators replaced by one PD motor per remaining joint, and a floor plane at `floor`."""
    spec = mujoco.MjSpec.from_file(str(robot.mjcf_path))
    for a in list(spec.actuators):
        spec.delete(a)
    for s in list(spec.sensors):
        spec.delete(s)
    dropped = {robot.joint_names[j] for j in np.flatnonzero(drop)}
    for j in list(spec.joints):
        if (fixed and j.type == mujoco.mjtJoint.mjJNT_FREE) or j.name in dropped:
            spec.delete(j)
    for k in list(spec.keys):
        spec.delete(k)
    kept = [j for j in range(robot.n_joints) if not drop[j]]
    for j in kept:
        a = spec.add_actuator()
        a.name = f"motor_{robot.joint_names[j]}"
        a.target = robot.joint_names[j]
        a.trntype = mujoco.mjtTrn.mjTRN_JOINT
        a.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        a.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        gain = np.zeros(10)
        gain[0] = kp[j]
        bias = np.zeros(10)
        bias[1], bias[2] = -kp[j], -kd[j]
        a.gainprm, a.biasprm = gain, bias
        a.ctrllimited = False
        if np.isfinite(limit[j]):
            a.forcelimited = True
            a.forcerange = [-limit[j], limit[j]]
    if floor is not None:
        plane = spec.worldbody.add_geom()
        plane.name = "physics_floor"
        plane.type = mujoco.mjtGeom.mjGEOM_PLANE
        plane.size = [0.0, 0.0, 0.05]
        plane.pos = [0.0, 0.0, floor]
    return spec.compile()


def _build(robot: Robot, drop: np.ndarray, fixed: bool, floor: float | None,
           kp: np.ndarray, kd: np.ndarray) -> ReplayModel:
    act = actuation(robot)
    model = _compiled(robot, drop, fixed, floor, kp, kd, act.limit)
    kept = [j for j in range(robot.n_joints) if not drop[j]]
    model.opt.timestep = 1.0 / act.control_rate_hz
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    if floor is None:
        model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    jid = np.array([model.joint(robot.joint_names[j]).id for j in kept])
    kept_ = np.array(kept)
    return ReplayModel(model=model, joints=kept_, qpos_adr=model.jnt_qposadr[jid].copy(),
                       dof_adr=model.jnt_dofadr[jid].copy(), kp=kp[kept_].copy(), kd=kd[kept_].copy(),
                       limit=act.limit[kept_].copy())


def fixed_model(robot: Robot) -> ReplayModel:
    """The fixed-base replay model (cached on the robot)."""
    key = "physics.fixed_model"
    if key not in robot.derived:
        act = actuation(robot)
        robot.derived[key] = _build(robot, leg_joints(robot), fixed=True, floor=None, kp=act.kp, kd=act.kd)
    return robot.derived[key]


def _hand_joints(robot: Robot) -> np.ndarray:
    names = {j for side in robot.spec.hands for j in robot.hand_joint_names(side)}
    return np.array([n in names for n in robot.joint_names])


def _foot_geoms(robot: Robot, model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """Geoms (in `model`) whose contact with the floor carries the robot: the collision geoms
    within 5 mm of the lowest point at the stance (as `dynamics.support_polygon`)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    groups = list(robot.spec.collision.geom_groups)
    cand = np.flatnonzero(np.isin(model.geom_group, groups) & (model.geom_bodyid > 0)
                          & ((model.geom_contype | model.geom_conaffinity) != 0))
    low = np.array([data.geom_xpos[g, 2] - _half_height(model, data, g) for g in cand])
    return cand[low <= low.min() + 0.005]


def _half_height(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> float:
    """How far a geom reaches below its centre (spheres, capsules, boxes exactly; else its rbound)."""
    s, r = model.geom_size[g], data.geom_xmat[g].reshape(3, 3)
    kind = model.geom_type[g]
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return float(s[0])
    if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        return float(abs(r[2, 2]) * s[1] + s[0])
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return float(np.abs(r[2]) @ s[:3])
    return float(model.geom_rbound[g])


#: Friction-to-normal impedance ratio of the feet's contacts, with elliptic (exact Coulomb)
#: friction cones. MuJoCo's soft contacts let a loaded foot creep sideways under any tangential
#: force (at impratio 1 a G1 foot slid 7 mm in seq_002, whose floor force stays at a third of
#: the friction limit: |F_xy|/F_z 0.18 at μ 0.6); MuJoCo's documentation recommends elliptic cones with a larger
#: impratio to make friction stiffer than the normal direction. At 10 that creep falls to
#: 2 mm, and a higher ratio changes nothing further (100: the same slips within 1 mm).
FOOT_IMPRATIO = 10.0
#: The feet's and floor's contact time constant (`geom_solref[0]`) in physics steps: the
#: stiffest MuJoCo's documentation allows for its step. At its default 0.02 s the loaded soles
#: sink 3 mm and the standing H1 rocked on them by 1.6° (its CoM ±25 mm) at rest; at 2 steps
#: 0.5° (7 mm), the G1 1 mm.
FOOT_TIMECONST_STEPS = 2.0


def standing_model(robot: Robot) -> tuple[ReplayModel, np.ndarray, np.ndarray]:
    """The standing replay model, its initial qpos (stance) and its foot geoms (cached)."""
    key = "physics.standing_model"
    if key in robot.derived:
        return robot.derived[key]
    stand = stance_pose(robot)
    _, floor = support_polygon(robot, stand)
    act = actuation(robot)
    legs = leg_joints(robot)
    stance = robot.spec.actuation.stance if robot.spec.actuation is not None else None
    kp, kd = act.kp.copy(), act.kd.copy()
    if stance is not None:
        kp[legs], kd[legs] = stance.kp, stance.kd
    rm = _build(robot, _hand_joints(robot), fixed=False, floor=floor, kp=kp, kd=kd)
    model = rm.model
    qpos0 = model.qpos0.copy()
    qpos0[rm.qpos_adr] = stand[rm.joints]
    feet = _foot_geoms(robot, model, qpos0)
    floor_geom = model.geom("physics_floor").id
    contype = np.zeros(model.ngeom, dtype=np.int32)
    contype[feet] = 1
    contype[floor_geom] = 1
    model.geom_contype[:] = contype
    model.geom_conaffinity[:] = contype
    model.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    model.opt.impratio = FOOT_IMPRATIO
    model.geom_solref[feet, 0] = model.geom_solref[floor_geom, 0] = FOOT_TIMECONST_STEPS * model.opt.timestep
    robot.derived[key] = (rm, qpos0, feet)
    return robot.derived[key]


def reference_at(cmd: Commands, times: np.ndarray, rate_hz: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q_ref, q̇_ref, τ_ff (K,n) at control-step `times`, each joint's time quantised to its
    group's command rate (a command is held until the next one)."""
    t50 = cmd.times
    tq = np.floor(times[:, None] * rate_hz[None, :] + 1e-9) / rate_hz[None, :]
    tq = np.clip(tq, t50[0], t50[-1])
    if len(t50) < 2:
        n = len(times)
        return np.repeat(cmd.q, n, 0), np.repeat(cmd.qd, n, 0), np.repeat(cmd.tau_ff, n, 0)
    spline = CubicHermiteSpline(t50, cmd.q, cmd.qd, axis=0)
    dspline = spline.derivative()
    if np.all(tq == tq[:, :1]):  # one rate for every joint: evaluate once per time
        t = tq[:, 0]
        q, qd = spline(t), dspline(t)
        tau = np.stack([np.interp(t, t50, cmd.tau_ff[:, j]) for j in range(cmd.q.shape[1])], 1)
        return q, qd, tau
    cols = range(cmd.q.shape[1])
    q = np.stack([spline(tq[:, j])[:, j] for j in cols], 1)
    qd = np.stack([dspline(tq[:, j])[:, j] for j in cols], 1)
    tau = np.stack([np.interp(tq[:, j], t50, cmd.tau_ff[:, j]) for j in cols], 1)
    return q, qd, tau


@dataclass(frozen=True)
class Rollout:
    """A replay at the control rate: per step k (time k·dt) the joints' state q, q̇ (K,m) before
    the step, the motor demand before clipping (K,m), the applied torque (K,m); `joints` maps the
    m columns to robot joints; `qpos` (K,nq) the full state positions."""

    dt: float
    joints: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    demand: np.ndarray
    torque: np.ndarray
    limit: np.ndarray
    qpos: np.ndarray


def _roll(robot: Robot, rm: ReplayModel, cmd: Commands, qpos0: np.ndarray,
          extra: np.ndarray | None = None) -> Rollout:
    """Roll `cmd` out on replay model `rm` from `qpos0` (reference at t=0 on the driven joints);
    `extra` (m,) feed-forward added to every step (the stance torques)."""
    act = actuation(robot)
    model = rm.model
    dt = float(model.opt.timestep)
    duration = (len(cmd.q) - 1) / cmd.fps
    steps = int(np.floor(duration / dt + 1e-9)) + 1
    times = np.arange(steps) * dt
    q_ref, qd_ref, tau = reference_at(cmd, times, act.rate_hz)
    j = rm.joints
    q_ref, qd_ref, tau = q_ref[:, j], qd_ref[:, j], tau[:, j]
    if extra is not None:
        tau = tau + extra
    kp, kd = rm.kp, rm.kd
    ctrl = q_ref + (tau + kd * qd_ref) / kp
    data = mujoco.MjData(model)
    data.qpos[:] = qpos0
    data.qpos[rm.qpos_adr] = q_ref[0]
    data.qvel[:] = 0.0
    data.qvel[rm.dof_adr] = qd_ref[0]
    size = mujoco.mj_stateSize(model, int(mujoco.mjtState.mjSTATE_FULLPHYSICS))
    initial = np.empty(size)
    mujoco.mj_getState(model, data, initial, int(mujoco.mjtState.mjSTATE_FULLPHYSICS))
    qpos_start, qvel_start = data.qpos.copy(), data.qvel.copy()
    state, _ = rollout.rollout(model, data, initial[None], ctrl[None, :-1] if steps > 1 else ctrl[None])
    t_off = mujoco.mj_stateSize(model, int(mujoco.mjtState.mjSTATE_TIME))
    nq, nv = model.nq, model.nv
    after = state[0]
    qpos = np.concatenate([qpos_start[None], after[:, t_off:t_off + nq]])[:steps]
    qvel = np.concatenate([qvel_start[None], after[:, t_off + nq:t_off + nq + nv]])[:steps]
    q, qd = qpos[:, rm.qpos_adr], qvel[:, rm.dof_adr]
    demand = kp * (ctrl - q) - kd * qd
    limit = rm.limit
    return Rollout(dt=dt, joints=j, q=q, qd=qd, demand=demand, torque=np.clip(demand, -limit, limit),
                   limit=limit, qpos=qpos)


@dataclass(frozen=True)
class FixedBaseReplay:
    rollout: Rollout
    #: Full joint array (T,n) of the simulated motion at the 50 Hz sample times (legs: reference).
    q50: np.ndarray


def replay_fixed(robot: Robot, cmd: Commands) -> FixedBaseReplay:
    """The commands played with the pelvis welded."""
    rm = fixed_model(robot)
    r = _roll(robot, rm, cmd, rm.model.qpos0.copy())
    return FixedBaseReplay(rollout=r, q50=_at_samples(r, cmd))


def _at_samples(r: Rollout, cmd: Commands) -> np.ndarray:
    """The simulated joints at the commands' sample times (others from the commands)."""
    k = np.minimum(np.round(cmd.times / r.dt).astype(int), len(r.q) - 1)
    q = cmd.q.copy()
    q[:, r.joints] = r.q[k]
    return q


def _contact_points(model: mujoco.MjModel, data: mujoco.MjData, feet: np.ndarray) -> np.ndarray:
    """World points (F,3) where each foot geom meets the floor: its lowest point."""
    return np.array([data.geom_xpos[g] - [0.0, 0.0, _half_height(model, data, int(g))] for g in feet])


def _inverse_model(robot: Robot, rm: ReplayModel) -> mujoco.MjModel:
    """The standing model without contacts, limits or other constraints (cached on the robot):
    `mj_inverse` on it gives the generalised forces of a motion, the floating base's six rows
    included."""
    key = "physics.standing_inverse_model"
    if key not in robot.derived or robot.derived[key][0] is not rm:
        model = rm.model.__copy__()
        model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT | mujoco.mjtDisableBit.mjDSBL_CONTACT
                                      | mujoco.mjtDisableBit.mjDSBL_LIMIT)
        robot.derived[key] = (rm, model)
    return robot.derived[key][1]


@dataclass(frozen=True)
class StanceSupport:
    """What the floor must supply for the standing robot to move its upper body along a motion
    with its legs still, per 50 Hz sample: the legs' feed-forward torque (T,m), the floor's
    force (T,3, world, N) and its multibody ZMP (T,2, world xy: the point on the floor about
    which the floor's moment has no horizontal part; inertia of every link, angular momentum
    included) and the floor's moment about the vertical through that point (T,, N·m)."""

    torque: np.ndarray
    force: np.ndarray
    zmp: np.ndarray
    yaw_moment: np.ndarray
    #: The whole-body CoM (T,3, world) of the rigid stance moving along the motion.
    com: np.ndarray


#: Ridge on the contact forces (1/N): among the forces that balance the base, the smallest.
_SUPPORT_RIDGE = 1e-3


def stance_torques(robot: Robot, rm: ReplayModel, qpos: np.ndarray, feet: np.ndarray,
                   q: np.ndarray | None = None, fps: float = 50.0) -> StanceSupport:
    """The feet carrying the body while the driven joints move along `q` (T,m; default: held
    at `qpos`), the legs still and the base at `qpos`'s pose.

    Whole-body inverse dynamics (`mj_inverse` with contacts and constraints off, central-
    difference accelerations at `fps`) gives each joint's torque and the wrench the floor must
    supply (the floating base's six rows). That wrench is shared among the foot contact points:
    a non-negative vertical force at each point and one horizontal force per foot, the smallest
    such forces that balance the base (non-negative least squares with a light ridge). The legs'
    feed-forward is their inverse-dynamics torque minus Jᵀf of those forces: with it the leg PD
    only corrects errors, so the robot stands as one rigid body on its feet. Where the motion's
    ZMP leaves the feet no non-negative vertical forces balance the base: the feed-forward is
    the nearest support, and the robot tips, as it should."""
    from scipy.optimize import nnls

    from embody.robot.dynamics import derivatives
    model = _inverse_model(robot, rm)
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    q = np.atleast_2d(qpos[rm.qpos_adr] if q is None else q)
    qd, qdd = derivatives(q, 1.0 / fps)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)  # mj_jac reads the bodies' com-based frames
    # the legs are still and the base at qpos: the contact points and their Jacobians are fixed
    points = _contact_points(model, data, feet)
    floor = float(points[:, 2].min())
    owner = model.geom_bodyid[feet]
    jac = np.zeros((len(feet), 3, model.nv))
    for i, g in enumerate(feet):
        mujoco.mj_jac(model, data, jac[i], None, points[i], int(owner[i]))
    cols = [jac[:, 2].T]  # unknowns: f_z at each point (≥ 0), then f_x, f_y per foot (free)
    for b in np.unique(owner):
        jb = np.zeros((3, model.nv))
        mujoco.mj_jac(model, data, jb, None, points[owner == b].mean(0), int(b))
        cols += [jb[0][:, None], jb[1][:, None]]
    jt = np.concatenate(cols, axis=1)  # (nv, unknowns): generalised force of each unknown
    root = np.arange(6)
    n_z, n_f = len(feet), jt.shape[1]
    ridge = _SUPPORT_RIDGE * np.eye(n_f)
    a = np.vstack([jt[root], ridge])
    # the same with each horizontal force split into two non-negative parts (for nnls)
    split = np.concatenate([jt[root][:, :n_z], jt[root][:, n_z:], -jt[root][:, n_z:]], axis=1)
    a_split = np.vstack([split, _SUPPORT_RIDGE * np.eye(split.shape[1])])
    base = model.body(robot.spec.root_body).id
    rot = data.xmat[base].reshape(3, 3).copy()
    origin = data.xpos[base].copy()
    height = origin[2] - floor
    gen = np.empty((len(q), model.nv))
    com = np.empty((len(q), 3))
    for t in range(len(q)):
        data.qpos[rm.qpos_adr] = q[t]
        data.qvel[:] = 0.0
        data.qvel[rm.dof_adr] = qd[t]
        data.qacc[:] = 0.0
        data.qacc[rm.dof_adr] = qdd[t]
        mujoco.mj_inverse(model, data)
        gen[t] = data.qfrc_inverse
        com[t] = data.subtree_com[base]
    # ridge least squares for every sample at once; where a vertical force comes out negative
    # (the bound active), non-negative least squares on that sample
    rhs = np.concatenate([gen[:, root], np.zeros((len(q), n_f))], axis=1)
    f = np.linalg.lstsq(a, rhs.T, rcond=None)[0].T  # (T, unknowns)
    for t in np.flatnonzero((f[:, :n_z] < 0).any(1)):
        x, _ = nnls(a_split, np.concatenate([rhs[t], np.zeros(split.shape[1] - n_f)]))
        f[t] = np.concatenate([x[:n_z], x[n_z:n_f] - x[n_f:]])
    torque = gen[:, rm.dof_adr] - f @ jt[rm.dof_adr].T
    force = gen[:, :3]  # the free joint's rows: world force, then moment in the base frame
    moment = gen[:, 3:6] @ rot.T
    # the floor wrench about the base origin, moved to the floor point with no horizontal moment
    fz = np.maximum(force[:, 2], 1e-9)
    zmp = np.stack([origin[0] - (moment[:, 1] + height * force[:, 0]) / fz,
                    origin[1] + (moment[:, 0] - height * force[:, 1]) / fz], axis=1)
    arm = np.concatenate([zmp - origin[:2], np.full((len(q), 1), -height)], axis=1)
    yaw = moment[:, 2] + np.cross(-arm, force)[:, 2]
    return StanceSupport(torque=torque, force=force, zmp=zmp, yaw_moment=yaw, com=com)


@dataclass(frozen=True)
class StandingReplay:
    """The standing replay and, per 50 Hz sample, how the robot stood: pelvis tilt (rad, from
    its start orientation), horizontal drift (m) and sinking (m) from the start; each foot's
    tilt (rad, from its start), how far its highest contact point rose (m) and how far it slid
    (m); the whole-body CoM's horizontal distance (m) from where the rigid stance puts it;
    `support`: the floor wrench the motion asks for (`stance_torques`)."""

    rollout: Rollout
    pelvis_tilt: np.ndarray
    pelvis_drift: np.ndarray
    pelvis_drop: np.ndarray
    foot_tilt: np.ndarray
    foot_lift: np.ndarray
    foot_slip: np.ndarray
    com_offset: np.ndarray
    support: StanceSupport


def replay_standing(robot: Robot, cmd: Commands) -> StandingReplay:
    """The commands played on the robot standing on the floor: arms, waist (and every other
    non-leg joint except the fingers) follow the commands; the legs hold the stance pose under
    PD at the YAML's `actuation.stance` gains (else their group's) plus the feed-forward of the
    feet carrying the moving body (`stance_torques`)."""
    rm, qpos0, feet = standing_model(robot)
    legs = leg_joints(robot)[rm.joints]
    stand = stance_pose(robot)
    held = Commands(fps=cmd.fps, q=cmd.q.copy(), qd=cmd.qd.copy(), tau_ff=cmd.tau_ff.copy(),
                    kp=cmd.kp, kd=cmd.kd)
    leg_cols = rm.joints[legs]
    held.q[:, leg_cols] = stand[leg_cols]
    held.qd[:, leg_cols] = 0.0
    support = stance_torques(robot, rm, qpos0, feet, held.q[:, rm.joints], cmd.fps)
    held.tau_ff[:, leg_cols] = support.torque[:, legs]
    r = _roll(robot, rm, held, qpos0)
    k = np.minimum(np.round(cmd.times / r.dt).astype(int), len(r.qpos) - 1)
    model = rm.model
    data = mujoco.MjData(model)
    n = len(k)
    tilt, drift, drop, com = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    bodies = sorted({int(model.geom_bodyid[g]) for g in feet})
    ftilt, flift, fslip = (np.zeros((n, len(bodies))) for _ in range(3))
    root = model.body(robot.spec.root_body).id
    data.qpos[:] = r.qpos[0]
    mujoco.mj_kinematics(model, data)
    p0 = data.xpos[root].copy()
    z0 = data.geom_xpos[feet, 2].copy()
    f0 = data.xpos[bodies, :2].copy()
    up0 = data.xmat[root].reshape(3, 3)[:, 2].copy()  # z axes at the start
    fup0 = data.xmat[bodies].reshape(-1, 3, 3)[:, :, 2].copy()
    owner = model.geom_bodyid[feet]
    mass = np.where(model.body_rootid == root, model.body_mass, 0.0)
    for i, s in enumerate(k):
        data.qpos[:] = r.qpos[s]
        mujoco.mj_kinematics(model, data)
        com[i] = np.linalg.norm(mass @ data.xipos[:, :2] / mass.sum() - support.com[i, :2])
        tilt[i] = np.arccos(np.clip(data.xmat[root].reshape(3, 3)[:, 2] @ up0, -1.0, 1.0))
        drift[i] = np.linalg.norm(data.xpos[root, :2] - p0[:2])
        drop[i] = p0[2] - data.xpos[root, 2]
        fslip[i] = np.linalg.norm(data.xpos[bodies, :2] - f0, axis=1)
        up = data.xmat[bodies].reshape(-1, 3, 3)[:, :, 2]
        ftilt[i] = np.arccos(np.clip((up * fup0).sum(1), -1.0, 1.0))
        for c, b in enumerate(bodies):
            flift[i, c] = np.max((data.geom_xpos[feet, 2] - z0)[owner == b])
    return StandingReplay(rollout=r, pelvis_tilt=tilt, pelvis_drift=drift, pelvis_drop=drop,
                          foot_tilt=ftilt, foot_lift=flift, foot_slip=fslip, com_offset=com,
                          support=support)
