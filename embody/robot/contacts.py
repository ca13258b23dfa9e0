"""MuJoCo's verdict on self-collision: penetrating contacts between non-adjacent bodies per frame.

The sphere proxies steer the optimiser; this is the exact check. For every frame the root sits
at its default pose, `mj_kinematics` + `mj_collision` run (positions only: no dynamics needed),
and we count penetrating contacts (dist < 0) between collision geoms of non-adjacent bodies,
skipping contacts inside one `ignore_subtrees` subtree (fingers closing on their own palm are by
design) and the robot's documented structural `ignore_pairs`.
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


def _frame_pairs(robot: Robot, q: np.ndarray) -> list[list[tuple[int, int]]]:
    """Per frame, the body pairs of every counted penetrating contact."""
    model = robot.model
    data = mujoco.MjData(model)
    groups = set(robot.spec.collision.geom_groups)
    parent = model.body_parentid
    ignored = [subtree_ids(model, b) for b in robot.spec.collision.ignore_subtrees]
    skip = {frozenset((model.body(a).id, model.body(b).id)) for a, b in robot.spec.collision.ignore_pairs}
    out = []
    for qt in np.atleast_2d(q):
        data.qpos[:] = robot.qpos(qt)
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        found = []
        for c in data.contact[: data.ncon]:
            if c.dist >= 0:
                continue
            g1, g2 = c.geom1, c.geom2
            if model.geom_group[g1] not in groups or model.geom_group[g2] not in groups:
                continue
            b1, b2 = int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2])
            if b1 == b2 or parent[b1] == b2 or parent[b2] == b1:
                continue
            if any(b1 in s and b2 in s for s in ignored) or frozenset((b1, b2)) in skip:
                continue
            found.append((b1, b2))
        out.append(found)
    return out


def self_collision_contacts(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Penetrating self-contacts per frame (T,)."""
    return np.array([len(f) for f in _frame_pairs(robot, q)], dtype=np.int64)


def contact_pairs(robot: Robot, q: np.ndarray) -> Counter:
    """Frames per penetrating body pair (names sorted), for breakdowns."""
    out: Counter = Counter()
    for found in _frame_pairs(robot, q):
        out.update({tuple(sorted((robot.model.body(a).name, robot.model.body(b).name))) for a, b in found})
    return out
