"""MuJoCo's verdict on self-collision: penetrating contacts between non-adjacent bodies per frame.

The sphere proxies steer the optimiser; this is the exact check. For every frame the root sits
at its default pose, `mj_kinematics` + `mj_collision` run (positions only: no dynamics needed),
and we count penetrating contacts (dist < 0) between collision geoms of non-adjacent bodies,
skipping only the robot's documented `ignore_pairs` (each with its kind and reason, checked at
load by `embody.robot.exclusions`): fingers of one hand against each other and against their
palm count like any other pair.
"""

from __future__ import annotations

from collections import Counter

import mujoco
import numpy as np

from embody.robot.model import Robot


def subtree_ids(model: mujoco.MjModel, root: str) -> set[int]:
    """Body ids of `root` and every body below it."""
    r = model.body(root).id
    out = {r}
    for b in range(model.nbody):
        p = b
        while p > 0:
            if p == r:
                out.add(b)
                break
            p = model.body_parentid[p]
    return out


def counted_geom_pairs(robot: Robot) -> np.ndarray:
    """(ngeom, ngeom) bool: contacts between these geoms count as self-collision."""
    model = robot.model
    g = np.arange(model.ngeom)
    in_group = np.isin(model.geom_group, list(robot.spec.collision.geom_groups))
    body = model.geom_bodyid
    parent = model.body_parentid
    b1, b2 = body[g][:, None], body[g][None, :]
    ok = in_group[:, None] & in_group[None, :] & (b1 != b2) & (parent[b1] != b2) & (parent[b2] != b1)
    for pair in robot.spec.collision.ignore_pairs:
        a, b = pair.bodies
        ia, ib = body == model.body(a).id, body == model.body(b).id
        ok &= ~((ia[:, None] & ib[None, :]) | (ib[:, None] & ia[None, :]))
    return ok


def collision_model(robot: Robot, margin: float = 0.0,
                    movable_only: bool = False) -> tuple[mujoco.MjModel, np.ndarray]:
    """A copy of the robot's model whose `mj_collision` reports the counted pairs' contacts and
    (almost) nothing else, and the (ngeom, ngeom) table of those pairs; cached on the robot.

    Geoms in no counted pair get no collision bits, and (`pair_bits`) geoms of bodies that are in
    no counted pair together never reach the narrow phase: the same counted contacts as
    `robot.model`, for less of its collision time (the verdict, the repair and the IK's polish
    run it per frame). `margin`: every used geom's margin (contacts closer
    than it are reported, dist ≥ 0 included). `movable_only`: only pairs whose relative pose
    the IK joints change (the IK's exact-contact rows; the verdict needs every counted pair).
    One contact per geom pair (`single_contact`): the same pairs and distances on every MuJoCo."""
    key = ("collision_model", float(margin), bool(movable_only))
    if key in robot.derived:
        return robot.derived[key]
    model = single_contact(robot.model.__copy__())
    counted = counted_geom_pairs(robot)
    contype, conaff = model.geom_contype.astype(np.int64), model.geom_conaffinity.astype(np.int64)
    counted &= ((contype[:, None] & conaff[None, :]) | (conaff[:, None] & contype[None, :])) != 0
    if movable_only:
        bodies = [model.body(int(b)).name for b in model.geom_bodyid]
        fk = robot.fk([b for b in bodies if model.body(b).id > 0])
        moves = fk.moves(list(np.flatnonzero(robot.ik_mask)))  # (J, walked bodies)
        moved = np.array([moves[:, fk.index[b]] if b in fk.index else np.zeros(len(moves))
                          for b in bodies]) > 0  # (ngeom, J): which IK joints move each geom
        counted &= (moved[:, None, :] != moved[None, :, :]).any(-1)
    used = counted.any(1)
    if (contype[used] == 1).all() and (conaff[used] == 1).all():  # else keep the model's own bits
        exact = pair_bits(model.geom_bodyid, counted)
        if exact is None:
            exact = exclusion_bits(model, counted)
        if exact is not None:
            contype, conaff = exact
    model.geom_contype[:] = np.where(used, contype, 0)
    model.geom_conaffinity[:] = np.where(used, conaff, 0)
    model.geom_margin[used] = margin
    robot.derived[key] = (model, counted)
    return robot.derived[key]


def single_contact(model: mujoco.MjModel) -> mujoco.MjModel:
    """`model`, changed in place, with MuJoCo's multi-point convex contacts off: one contact per
    geom pair, the deepest. Why: with them on (both versions' default), mujoco 4.0's mesh pairs
    report 3-4 points whose deepest differs from the single point's by -0.10..+0.43 mm (3.11's
    extra points share the single point's depth), so counts and distances depended on the
    version; with them off 3.11 and 4.0 report the same pairs and counts and the same distances
    to 1.2 µm (410 G1 poses, margins 0 and 2 mm)."""
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_MULTICCD)
    return model


def pair_bits(geom_body: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """contype/conaffinity bits (ngeom,) under which MuJoCo's bitmask filter passes exactly the
    geom pairs `pairs` (ngeom, ngeom) bool, symmetric, or None when that cannot be said in 31
    bits. Bodies whose geoms pair with the same bodies share a bit; a geom's affinity is the OR
    of the bits its body pairs with. Only possible when `pairs` is a relation between bodies.
    Why: geoms that are in some counted pair but not with each other (G1's legs and pelvis among
    themselves, which the IK joints do not move relative to each other) otherwise reach MuJoCo's
    narrow phase on every call for contacts that are thrown away (~12 % of the exact-contact
    model's `mj_collision` time); the pairs it keeps, and so their contacts, are the same."""
    used = pairs.any(1)
    bodies = np.unique(geom_body[used])
    rel = np.zeros((len(bodies), len(bodies)), dtype=bool)  # body pairs with a counted geom pair
    idx = np.searchsorted(bodies, geom_body)
    a, b = np.nonzero(pairs)
    rel[idx[a], idx[b]] = True
    g = np.flatnonzero(used)
    if not np.array_equal(pairs[np.ix_(g, g)], rel[np.ix_(idx[g], idx[g])] & (geom_body[g, None] != geom_body[None, g])):
        return None  # not a body relation
    _, group = np.unique(rel, axis=0, return_inverse=True)
    group = np.asarray(group).reshape(-1)
    if group.max(initial=0) >= 31:
        return None
    bit = np.left_shift(1, group).astype(np.int64)  # per body
    affinity = np.array([np.bitwise_or.reduce(bit[row], initial=0) for row in rel], dtype=np.int64)
    contype, conaff = np.zeros(len(geom_body), np.int64), np.zeros(len(geom_body), np.int64)
    contype[g], conaff[g] = bit[idx[g]], affinity[idx[g]]
    return contype, conaff


def exclusion_bits(model: mujoco.MjModel, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """contype/conaffinity bits (ngeom,) under which MuJoCo (its bitmask filter, plus its own
    skipping of one body's geoms and of a parent's with its child's) passes exactly `pairs`
    among the geoms in some pair, or None when `pairs` is not "every pair of used geoms but a few
    body pairs X" with the bodies of X fitting in 30 bits. Bodies in no pair of X get bit 0 in
    contype and every bit in conaffinity; each body s in X gets a bit of its own b_s, contype b_s
    and conaffinity bit 0 plus the bits of the X bodies it may meet. Why: `pair_bits` needs one
    bit per distinct row of the body relation, and with the fingers of a hand counted (each
    finger meets its own set of bodies) G1's verdict has 42, past MuJoCo's 31 bits."""
    g = np.flatnonzero(pairs.any(1))
    body, parent = model.geom_bodyid, model.body_parentid
    b1, b2 = body[g][:, None], body[g][None, :]
    skipped = (b1 == b2) | (parent[b1] == b2) | (parent[b2] == b1)  # MuJoCo's own filters
    left_out = ~pairs[np.ix_(g, g)] & ~skipped  # geom pairs the bits must stop
    xa, xb = np.nonzero(left_out)
    x = {(int(body[g][i]), int(body[g][j])) for i, j in zip(xa, xb)}
    members = sorted({b for pair in x for b in pair})
    if len(members) > 30:
        return None
    bit = {b: 1 << (k + 1) for k, b in enumerate(members)}
    every = (1 << (len(members) + 1)) - 1
    contype, conaff = np.zeros(model.ngeom, np.int64), np.zeros(model.ngeom, np.int64)
    for i in g:
        b = int(body[i])
        if b in bit:
            contype[i] = bit[b]
            conaff[i] = 1 | sum(bit[o] for o in members if (b, o) not in x)
        else:
            contype[i], conaff[i] = 1, every
    ct, ca = contype[g], conaff[g]
    passes = (((ct[:, None] & ca[None]) | (ca[:, None] & ct[None])) != 0) & ~skipped
    if not np.array_equal(passes, pairs[np.ix_(g, g)] & ~skipped) or (pairs[np.ix_(g, g)] & skipped).any():
        return None  # not of that form
    return contype, conaff


def counted_contacts(robot: Robot, q: np.ndarray, gap: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame of q (T,n), the counted contacts closer than `gap` (m; 0: penetrating): their
    (geom1, geom2) pairs (k, 2) and MuJoCo's distances (k,), negative inside."""
    model, counted = collision_model(robot, margin=gap)
    data = mujoco.MjData(model)
    out = []
    none = (np.zeros((0, 2), dtype=np.int32), np.zeros(0))
    data.qpos[:] = model.qpos0
    for qt in np.atleast_2d(q):
        data.qpos[robot.qpos_adr] = qt
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        if not data.ncon:  # most poses: nothing to filter
            out.append(none)
            continue
        geom, dist = data.contact.geom[: data.ncon], data.contact.dist[: data.ncon]
        hit = (dist < gap) & counted[geom[:, 0], geom[:, 1]]
        out.append((geom[hit], dist[hit].copy()))
    return out


def near_contacts(robot: Robot, q: np.ndarray, gap: float) -> np.ndarray:
    """Per frame (T,), the counted pairs closer than `gap` (m): `self_collision_contacts` with a
    clearance, for an array that must keep its pairs apart by more than a tracking error."""
    return np.array([len(pairs) for pairs, _ in counted_contacts(robot, q, gap)], dtype=np.int64)


def self_collision_contacts(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Penetrating self-contacts per frame (T,)."""
    return near_contacts(robot, q, 0.0)


def contact_pairs(robot: Robot, q: np.ndarray) -> Counter:
    """Frames per penetrating body pair (names sorted), for breakdowns."""
    out: Counter = Counter()
    body = robot.model.geom_bodyid
    for found, _ in counted_contacts(robot, q):
        out.update({tuple(sorted((robot.model.body(body[a]).name, robot.model.body(body[b]).name)))
                    for a, b in found})
    return out
