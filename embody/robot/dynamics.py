"""Rigid-body dynamics of a joint trajectory: effort limits, inverse-dynamics torque and the ZMP.

A kinematically valid trajectory can still ask a motor for more torque than it has, or tip a
standing robot over. These are the quantities that say so, computed with MuJoCo on the robot's
own MJCF. Joint arrays follow `robot.joint_names` (MuJoCo qpos order, free joint left out).

- Torques are *free-motion, fixed-base*: the root stays at its default pose with zero velocity
  and acceleration, and contacts, joint limits and every other constraint are disabled, so the
  torque is what the motors need to move the links along the trajectory (`mj_inverse`: mass
  matrix, bias forces, minus passive forces such as joint damping), plus the joints' dry friction
  (`frictionloss`, which the motors overcome too). The velocity and
  acceleration are those of the curve the robot is commanded along between the samples: the
  natural cubic spline through them (`spline_derivatives`, what `physics.commands` sends).
- The ZMP is the cart-table ZMP of the robot standing on a flat floor: legs at the stance pose,
  the whole-body CoM from MuJoCo's subtree CoM of the root, CoM acceleration from central
  differences at the trajectory's rate.
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.robot.model import Robot

GRAVITY = 9.81
_FREE_DISABLE = (mujoco.mjtDisableBit.mjDSBL_CONSTRAINT | mujoco.mjtDisableBit.mjDSBL_CONTACT
                 | mujoco.mjtDisableBit.mjDSBL_LIMIT)


def joint_ids(robot: Robot) -> np.ndarray:
    return np.array([robot.model.joint(n).id for n in robot.joint_names], dtype=np.int64)


def dof_adr(robot: Robot) -> np.ndarray:
    """qvel/qfrc address of every joint in `robot.joint_names` order."""
    return robot.model.jnt_dofadr[joint_ids(robot)].astype(np.int64)


def effort_limits(robot: Robot) -> np.ndarray:
    """Per joint, the largest torque its motor gives (N·m), np.inf where the model sets none.

    Read from the joint's `actuatorfrcrange` (Menagerie G1). A joint without one but driven by a
    plain torque motor (gain only, no bias: Menagerie H1's `<motor ctrlrange>`) gets the motor's
    `ctrlrange` × gain × gear, or its `forcerange` when that is set, which is the same bound."""
    m = robot.model
    jid = joint_ids(robot)
    lim = np.full(len(jid), np.inf)
    limited = m.jnt_actfrclimited[jid].astype(bool)
    rng = m.jnt_actfrcrange[jid]
    lim[limited] = np.minimum(np.abs(rng[limited, 0]), np.abs(rng[limited, 1]))
    where = {int(j): k for k, j in enumerate(jid)}
    for a in range(m.nu):
        k = where.get(int(m.actuator_trnid[a, 0]))
        if k is None or limited[k] or m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
            continue
        gear, gain = abs(float(m.actuator_gear[a, 0])), float(m.actuator_gainprm[a, 0])
        bound = np.inf
        if m.actuator_forcelimited[a]:
            bound = float(np.min(np.abs(m.actuator_forcerange[a])))
        elif m.actuator_ctrllimited[a] and not np.any(m.actuator_biasprm[a, :3]):
            bound = float(np.min(np.abs(m.actuator_ctrlrange[a]))) * abs(gain)
        lim[k] = min(lim[k], bound * gear)
    return lim


def derivatives(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration (T,n) of samples q (T,n) taken every `dt` seconds.

    Interior samples: central differences, qd = (q[t+1]-q[t-1])/2dt and
    qdd = (q[t+1]-2q[t]+q[t-1])/dt². End samples: one-sided, qd = first forward/backward
    difference and qdd = the neighbouring sample's (the one-sided second difference). A single
    sample has zero derivatives."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if len(q) < 2:
        return np.zeros_like(q), np.zeros_like(q)
    qd = np.gradient(q, dt, axis=0, edge_order=1)
    qdd = np.zeros_like(q)
    if len(q) >= 3:
        qdd[1:-1] = (q[2:] - 2.0 * q[1:-1] + q[:-2]) / dt**2
        qdd[0], qdd[-1] = qdd[1], qdd[-2]
    return qd, qdd


def spline_derivatives(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration (T,n) at the samples of the natural cubic spline through q (T,n)
    taken every `dt` seconds. Why this curve: a robot stack plays samples by interpolating them
    (the replay: a cubic Hermite spline on q and q̇), and of all twice-differentiable curves
    through the samples the natural cubic spline has the least ∫q̈²; with its own q̇ as the
    commanded velocity its acceleration is continuous and linear between samples, so torques
    at the samples bound the torque the motors are asked for in between. Central differences
    disagree with it by the third difference (a 50 Hz zig-zag needs 3× their acceleration).
    Fewer than 3 samples: the straight line (2) or rest (1)."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if len(q) < 2:
        return np.zeros_like(q), np.zeros_like(q)
    if len(q) == 2:
        v = np.repeat((q[1:] - q[:1]) / dt, 2, axis=0)
        return v, np.zeros_like(q)
    acc = spline_acceleration_matrix(len(q), dt) @ q
    # slopes from the knot accelerations (natural spline): exact, no second solve
    d = np.diff(q, axis=0) / dt
    qd = np.empty_like(q)
    qd[:-1] = d - dt * (2.0 * acc[:-1] + acc[1:]) / 6.0
    qd[-1] = d[-1] + dt * (acc[-2] + 2.0 * acc[-1]) / 6.0
    return qd, acc


def spline_acceleration_matrix(t: int, dt: float) -> np.ndarray:
    """(T,T) the linear map from samples to the natural cubic spline's knot accelerations:
    (a[k-1] + 4 a[k] + a[k+1]) / 6 = (q[k+1] − 2 q[k] + q[k-1]) / dt², a[0] = a[T-1] = 0. Its
    rows decay as 0.268^|k−j| away from the diagonal (cached per length)."""
    key = (int(t), float(dt))
    if key not in _SPLINE_CACHE:
        if t < 3:
            _SPLINE_CACHE[key] = np.zeros((t, t))
        else:
            from scipy.linalg import solve_banded
            n = t - 2
            band = np.zeros((3, n))
            band[0, 1:], band[1], band[2, :-1] = 1.0 / 6.0, 4.0 / 6.0, 1.0 / 6.0
            d2 = np.zeros((n, t))
            k = np.arange(n)
            d2[k, k], d2[k, k + 1], d2[k, k + 2] = 1.0, -2.0, 1.0
            out = np.zeros((t, t))
            out[1:-1] = solve_banded((1, 1), band, d2 / dt**2)
            if len(_SPLINE_CACHE) > 64:
                _SPLINE_CACHE.clear()
            _SPLINE_CACHE[key] = out
    return _SPLINE_CACHE[key]


_SPLINE_CACHE: dict[tuple[int, float], np.ndarray] = {}


def free_motion_model(robot: Robot) -> mujoco.MjModel:
    """The robot's model with contacts, joint limits and constraints disabled (cached)."""
    key = "dynamics.free_motion_model"
    if key not in robot.derived:
        model = robot.model.__copy__()
        model.opt.disableflags |= int(_FREE_DISABLE)
        robot.derived[key] = model
    return robot.derived[key]


def inverse_dynamics(robot: Robot, q: np.ndarray, dt: float, qd: np.ndarray | None = None,
                     qdd: np.ndarray | None = None, friction: bool = True) -> np.ndarray:
    """Joint torques (T,n) that move the fixed-base robot along q (T,n) in free motion.

    `qd`/`qdd` default to `spline_derivatives(q, dt)`: the commanded curve's. Includes the dry
    friction against the motion (`friction_torque`) unless `friction` is False. With the root's velocity and acceleration zero,
    the joint rows of `mj_inverse` are exactly the torques of the robot with its pelvis welded."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if qd is None or qdd is None:
        d_qd, d_qdd = spline_derivatives(q, dt)
        qd = d_qd if qd is None else qd
        qdd = d_qdd if qdd is None else qdd
    model = free_motion_model(robot)
    data = mujoco.MjData(model)
    dof = dof_adr(robot)
    data.qpos[:] = model.qpos0
    tau = np.empty_like(q)
    for t in range(len(q)):
        data.qpos[robot.qpos_adr] = q[t]
        data.qvel[:] = 0.0
        data.qvel[dof] = qd[t]
        data.qacc[:] = 0.0
        data.qacc[dof] = qdd[t]
        mujoco.mj_inverse(model, data)
        tau[t] = data.qfrc_inverse[dof]
    return tau + friction_torque(robot, qd) if friction else tau


#: Joint speed (rad/s) over which the dry-friction torque ramps up to its full value (a smooth
#: sign: at rest the friction holds whatever is needed, up to its bound).
FRICTION_SPEED = 0.05


def friction_torque(robot: Robot, qd: np.ndarray) -> np.ndarray:
    """The joints' dry friction (T,n) against motion at velocities qd: the MJCF's `frictionloss`
    × tanh(qd / FRICTION_SPEED). Why: MuJoCo applies `frictionloss` as a constraint, which the
    free-motion model (constraints off) leaves out, yet the motors pay it (the G1's is 0.3 N·m
    on every joint: a fifth of a Dex3 finger's 1.4 N·m)."""
    loss = robot.model.dof_frictionloss[dof_adr(robot)]
    return loss * np.tanh(np.atleast_2d(qd) / FRICTION_SPEED)


def torque_ratio(robot: Robot, tau: np.ndarray) -> np.ndarray:
    """|tau| / effort limit (T,n); 0 where a joint is unlimited."""
    return np.abs(np.atleast_2d(tau)) / effort_limits(robot)


# --- standing balance -------------------------------------------------------------------------

def leg_joints(robot: Robot) -> np.ndarray:
    """Bool (n,): joints below the root that carry neither the torso nor anything on it (the
    legs): a joint whose body is neither an ancestor of the torso body nor inside its subtree."""
    key = "dynamics.leg_joints"
    if key not in robot.derived:
        robot.derived[key] = _leg_joints(robot)
    return robot.derived[key].copy()


def _leg_joints(robot: Robot) -> np.ndarray:
    m = robot.model
    torso = m.body(robot.spec.torso_body).id
    chain = {torso}
    b = torso
    while b > 0:
        b = int(m.body_parentid[b])
        chain.add(b)

    def under_torso(body: int) -> bool:
        while body > 0:
            if body == torso:
                return True
            body = int(m.body_parentid[body])
        return False

    bodies = m.jnt_bodyid[joint_ids(robot)]
    return np.array([int(b) not in chain and not under_torso(int(b)) for b in bodies])


def stance_pose(robot: Robot) -> np.ndarray:
    """Leg joint values (n,) of the standing robot (other joints at the T-pose): Menagerie's
    `stand` keyframe where the model has it, else the robot YAML's `actuation.stance.pose`,
    else the YAML T-pose."""
    key = "dynamics.stance_pose"
    if key not in robot.derived:
        robot.derived[key] = _stance_pose(robot)
    return robot.derived[key].copy()


def _stance_pose(robot: Robot) -> np.ndarray:
    q = robot.tpose.copy()
    m = robot.model
    legs = leg_joints(robot)
    names = [m.key(k).name for k in range(m.nkey)]
    actuation = getattr(robot.spec, "actuation", None)  # a spec from before `actuation` existed: none
    stance = actuation.stance if actuation is not None else None
    if "stand" in names:
        q[legs] = m.key("stand").qpos[robot.qpos_adr][legs]
    elif stance is not None and stance.pose:
        for name, value in stance.pose.items():
            q[robot.joint_index(name)] = value
    return q


def _foot_points(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray) -> np.ndarray:
    """World points (K,3) at the bottom of each geom (spheres: centre; capsules: both end
    centres; boxes: the 8 corners; meshes: vertices), before keeping the lowest."""
    pts = []
    for g in geoms:
        c, r, s = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
        kind = model.geom_type[g]
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            pts.append(c[None] - [0, 0, s[0]])
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE or kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            ax = r[:, 2] * s[1]
            pts.append(np.stack([c + ax, c - ax]) - [0, 0, s[0]])
        elif kind == mujoco.mjtGeom.mjGEOM_BOX:
            corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) * s
            pts.append(c + corners @ r.T)
        elif kind == mujoco.mjtGeom.mjGEOM_MESH:
            mid = model.geom_dataid[g]
            a, n = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
            pts.append(c + model.mesh_vert[a:a + n].astype(np.float64) @ r.T)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (K,2) of 2-D points (Andrew's monotone chain)."""
    p = np.unique(np.round(np.asarray(points, dtype=np.float64), 12), axis=0)
    if len(p) < 3:
        return p

    def half(pts: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for x in pts:
            while len(out) >= 2 and _cross(out[-1] - out[-2], x - out[-2]) <= 0:
                out.pop()
            out.append(x)
        return out

    lower, upper = half(p), half(p[::-1])
    return np.array(lower[:-1] + upper[:-1])


def polygon_margin(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distance (T,) of 2-D points to a CCW convex polygon's boundary: positive inside."""
    p = np.atleast_2d(points)[:, None, :]
    a, b = polygon, np.roll(polygon, -1, axis=0)
    e = b - a
    length = np.linalg.norm(e, axis=1)
    inward = np.stack([-e[:, 1], e[:, 0]], axis=1) / length[:, None]  # left normal = inside (CCW)
    line = ((p - a) * inward).sum(-1)  # (T,K)
    s = np.clip(((p - a) * e).sum(-1) / length**2, 0.0, 1.0)
    seg = np.linalg.norm(p - (a + s[..., None] * e), axis=-1)
    inside = (line >= 0).all(1)
    return np.where(inside, line.min(1), -seg.min(1))


def support_polygon(robot: Robot, q_stand: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The feet's support polygon (K,2, CCW, world xy) and the floor height (m) at the stance.

    Foot geoms are the collision geoms (the robot's `collision.geom_groups`, with contact bits)
    whose lowest point lies within 5 mm of the robot's lowest; their bottom points within 5 mm
    of the floor span the polygon."""
    q = stance_pose(robot) if q_stand is None else np.asarray(q_stand, dtype=np.float64)
    key = ("dynamics.support_polygon", q.tobytes())
    if key not in robot.derived:
        robot.derived[key] = _support_polygon(robot, q)
    polygon, floor = robot.derived[key]
    return polygon.copy(), floor


def _support_polygon(robot: Robot, q: np.ndarray) -> tuple[np.ndarray, float]:
    m = robot.model
    data = mujoco.MjData(m)
    data.qpos[:] = robot.qpos(q)
    mujoco.mj_kinematics(m, data)
    geoms = np.flatnonzero(np.isin(m.geom_group, list(robot.spec.collision.geom_groups))
                           & ((m.geom_contype | m.geom_conaffinity) != 0) & (m.geom_bodyid > 0))
    per = [_foot_points(m, data, np.array([g])) for g in geoms]
    lows = np.array([p[:, 2].min() if len(p) else np.inf for p in per])
    floor = float(lows.min())
    pts = np.concatenate([p for p, lo in zip(per, lows) if lo <= floor + 0.005])
    pts = pts[pts[:, 2] <= floor + 0.005]
    return convex_hull(pts[:, :2]), floor


def standing_q(robot: Robot, q: np.ndarray) -> np.ndarray:
    """q (T,n) with the legs at the stance pose."""
    q = np.array(np.atleast_2d(q), dtype=np.float64)
    legs = leg_joints(robot)
    q[:, legs] = stance_pose(robot)[legs]
    return q


def center_of_mass(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Whole-body CoM (T,3) in the world frame, root at its default pose."""
    m = robot.model
    data = mujoco.MjData(m)
    data.qpos[:] = m.qpos0
    root = m.body(robot.spec.root_body).id
    out = np.empty((len(q), 3))
    for t, qt in enumerate(np.atleast_2d(q)):
        data.qpos[robot.qpos_adr] = qt
        mujoco.mj_kinematics(m, data)
        mujoco.mj_comPos(m, data)
        out[t] = data.subtree_com[root]
    return out


def zmp(robot: Robot, q: np.ndarray, dt: float, stance: np.ndarray | None = None
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cart-table ZMP (T,2) of the robot standing with its upper body moving along q (T,n), the
    support polygon (K,2) and the ZMP's signed margin (T,) inside it (m, positive inside).

    The legs are held at `stance` (default `stance_pose(robot)`), feet flat on the floor under the
    root's default pose. ZMP = c_xy - c_z · c̈_xy / (c̈_z + g), c̈ by `derivatives` at `dt`,
    c_z above the floor."""
    q_legs = stance_pose(robot) if stance is None else np.asarray(stance, dtype=np.float64)
    legs = leg_joints(robot)
    q = np.array(np.atleast_2d(q), dtype=np.float64)
    q[:, legs] = q_legs[legs]
    stand_pose = robot.tpose.copy()
    stand_pose[legs] = q_legs[legs]
    polygon, floor = support_polygon(robot, stand_pose)
    com = center_of_mass(robot, q)
    _, cdd = derivatives(com, dt)
    height = com[:, 2] - floor
    point = com[:, :2] - height[:, None] * cdd[:, :2] / (cdd[:, 2:3] + GRAVITY)
    return point, polygon, polygon_margin(point, polygon)
