"""The robot YAML's excluded collision pairs, checked against the robot's own geometry at load.

Every contact between collision geoms of two bodies counts as self-collision (the verdict, the
IK, the repair, the export) unless the pair is listed in `collision.ignore_pairs`, and a listed
pair must be one that touches by construction:
  * `joint`: a joint's two links (parent and child), which MuJoCo never reports anyway; listed
    to record how deep their geoms sit in each other;
  * `always`: a pair in contact at every pose: the joints on the path between the two bodies
    are sampled over their ranges (`SAMPLES` seeded uniform poses) and the pair must penetrate
    at each one; a single clear pose means the exclusion hides real collisions (a thumb
    stalling against the index finger) and the robot is refused;
Nothing else may be listed: a housing that grazes its mount over part of its range (G1's and
H1's shoulder-roll housings on the torso shell, 10-39 % of shoulder poses) collides there for
real, so it is counted, and the IK keeps out of it through its proxies.
Why: a blanket exclusion (every contact inside a wrist's subtree) once hid fingers up to 26 mm
through each other from every counter.

The MJCF's own `<exclude>` pairs hide contacts from MuJoCo (so from every counter) as well: one
listed in `collision.ignore_pairs` is checked like any listed pair (its depths measured with the
MJCF exclusions lifted); an unlisted one is lifted (`lift_unlisted_excludes`), so it counts.
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.errors import ConfigError
from embody.robot.spec import RobotSpec

#: Poses sampled per `always` pair.
SAMPLES = 300


def ancestors(model: mujoco.MjModel, b: int) -> list[int]:
    out = [b]
    while b > 0:
        b = int(model.body_parentid[b])
        out.append(b)
    return out


def path_joints(model: mujoco.MjModel, a: int, b: int) -> list[int]:
    """Hinge joints (ids) whose motion changes the relative pose of bodies a and b."""
    up_a, up_b = ancestors(model, a), ancestors(model, b)
    common = next(x for x in up_a if x in up_b)
    bodies = [x for x in up_a[: up_a.index(common)]] + [x for x in up_b[: up_b.index(common)]]
    return [j for j in range(model.njnt) if model.jnt_bodyid[j] in bodies
            and model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]


def hand_roots(model: mujoco.MjModel, spec: RobotSpec) -> list[int]:
    """Per hand, the body every finger hangs from (the lowest common ancestor of its joints)."""
    roots = []
    for fingers in spec.hands.values():
        chains = [ancestors(model, int(model.jnt_bodyid[model.joint(j).id]))[1:]
                  for joints in fingers.values() for j in joints[:1]]
        if chains:
            roots.append(next(x for x in chains[0] if all(x in c for c in chains)))
    return roots


def mjcf_excludes(model: mujoco.MjModel) -> list[tuple[int, int]]:
    """Body id pairs the MJCF itself `<exclude>`s."""
    return [(int(s) >> 16, int(s) & 0xFFFF) for s in model.exclude_signature]


def pair_depths(model: mujoco.MjModel, a: int, b: int, groups: list[int], samples: int = SAMPLES,
                seed: int = 0) -> np.ndarray:
    """Deepest signed distance (m; ≥ 0: clear) between the collision geoms of bodies a and b at
    `samples` seeded uniform poses of the joints between them (the rest at qpos0)."""
    from embody.robot.contacts import single_contact  # contacts → model → this module

    m = single_contact(model.__copy__())  # the verdict's one contact a pair: same depths any MuJoCo
    geoms = np.flatnonzero(np.isin(m.geom_bodyid, [a, b]) & np.isin(m.geom_group, groups))
    m.geom_contype[:] = 0
    m.geom_conaffinity[:] = 0
    m.geom_contype[geoms] = 1
    m.geom_conaffinity[geoms] = 1
    m.geom_margin[geoms] = 0.0
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    m.exclude_signature[:] = 0  # the MJCF's own exclusions lifted (world-world: no geoms)
    d = mujoco.MjData(m)
    joints = path_joints(m, a, b)
    lo, hi = m.jnt_range[joints, 0], m.jnt_range[joints, 1]
    limited = m.jnt_limited[joints].astype(bool)
    lo, hi = np.where(limited, lo, -np.pi), np.where(limited, hi, np.pi)
    adr = m.jnt_qposadr[joints]
    rng = np.random.default_rng(seed)
    out = np.zeros(samples)
    for k in range(samples):
        d.qpos[:] = m.qpos0
        d.qpos[adr] = rng.uniform(lo, hi)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        dist = [d.contact.dist[i] for i in range(d.ncon)
                if {int(m.geom_bodyid[g]) for g in d.contact.geom[i]} == {a, b}]
        out[k] = min(dist, default=np.inf)
    return out


def lift_unlisted_excludes(model: mujoco.MjModel, spec: RobotSpec) -> mujoco.MjModel:
    """The model with every MJCF `<exclude>` not in `collision.ignore_pairs` lifted (a copy when
    there is one): MuJoCo then reports that pair's contacts like any other counted pair's."""
    listed = {frozenset(p.bodies) for p in spec.collision.ignore_pairs}
    lift = [i for i, (a, b) in enumerate(mjcf_excludes(model))
            if frozenset((model.body(a).name, model.body(b).name)) not in listed]
    if not lift:
        return model
    model = model.__copy__()
    model.exclude_signature[lift] = 0  # world–world: no geoms, so no exclusion
    return model


def check_ignored_pairs(model: mujoco.MjModel, spec: RobotSpec, where: str) -> None:
    """ConfigError (one line naming `<where>:collision.ignore_pairs.<i>`) for an excluded pair
    that does not touch by construction (module docstring)."""
    for i, pair in enumerate(spec.collision.ignore_pairs):
        key = f"{where}:collision.ignore_pairs.{i}"
        ids = []
        for name in pair.bodies:
            try:
                ids.append(model.body(name).id)
            except KeyError:
                raise ConfigError(f"{key}.bodies", f"no body {name!r} in the MJCF") from None
        a, b = ids
        label = f"{pair.bodies[0]}–{pair.bodies[1]}"
        if pair.kind == "joint":
            if model.body_parentid[a] != b and model.body_parentid[b] != a:
                raise ConfigError(key, f"{label} is not a joint's two links (neither is the other's parent)")
        else:
            depth = pair_depths(model, a, b, spec.collision.geom_groups)
            clear = int((depth >= 0).sum())
            if clear:
                raise ConfigError(key, f"{label} is not in contact at every pose: clear at {clear} of "
                                       f"{len(depth)} sampled poses of the joints between them "
                                       "(only a joint's two links or a pair always in contact may be excluded)")
