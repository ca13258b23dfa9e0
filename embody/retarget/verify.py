"""MuJoCo verification of a joint trajectory: exact self-collision contacts plus tracking metrics.

The sphere proxies steer the optimiser; this is the verdict. For every frame `mj_forward` runs
with the root at its default pose and we count penetrating contacts (dist < 0) between collision
geoms of non-adjacent bodies, skipping contacts inside one `ignore_subtrees` subtree (fingers
closing on their own palm are by design) and the robot's structural `ignore_pairs`.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np
import pandas as pd

from embody.retarget.ik import IKSolution, evaluate
from embody.retarget.targets import Targets
from embody.robot import Robot


def _subtree_ids(model: mujoco.MjModel, root: str) -> set[int]:
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


def self_collision_contacts(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Penetrating self-contacts per frame (T,)."""
    model = robot.model
    data = mujoco.MjData(model)
    groups = set(robot.spec.collision.geom_groups)
    parent = model.body_parentid
    ignored = [_subtree_ids(model, b) for b in robot.spec.collision.ignore_subtrees]
    pairs = {frozenset((model.body(a).id, model.body(b).id)) for a, b in robot.spec.collision.ignore_pairs}
    counts = np.zeros(len(q), dtype=np.int64)
    for t, qt in enumerate(np.atleast_2d(q)):
        data.qpos[:] = robot.qpos(qt)
        mujoco.mj_forward(model, data)
        for c in data.contact[: data.ncon]:
            if c.dist >= 0:
                continue
            g1, g2 = c.geom1, c.geom2
            if model.geom_group[g1] not in groups or model.geom_group[g2] not in groups:
                continue
            b1, b2 = model.geom_bodyid[g1], model.geom_bodyid[g2]
            if b1 == b2 or parent[b1] == b2 or parent[b2] == b1:
                continue
            if any(b1 in s and b2 in s for s in ignored) or frozenset((b1, b2)) in pairs:
                continue
            counts[t] += 1
    return counts


def verify(robot: Robot, solution: IKSolution | np.ndarray, targets: Targets) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Per-frame metrics table and aggregates (self-collision frames should be 0)."""
    q = solution.q if isinstance(solution, IKSolution) else np.asarray(solution)
    frames, metrics = evaluate(robot, q, targets)
    contacts = self_collision_contacts(robot, q)
    table = pd.DataFrame({
        "wrist_pos_err_mm_left": frames["wrist_pos_err_mm"][:, 0],
        "wrist_pos_err_mm_right": frames["wrist_pos_err_mm"][:, 1],
        "wrist_rot_err_deg_left": frames["wrist_rot_err_deg"][:, 0],
        "wrist_rot_err_deg_right": frames["wrist_rot_err_deg"][:, 1],
        "elbow_pos_err_mm_left": frames["elbow_pos_err_mm"][:, 0],
        "elbow_pos_err_mm_right": frames["elbow_pos_err_mm"][:, 1],
        "self_contacts": contacts,
    })
    metrics = dict(metrics)
    metrics["self_collision_frames"] = float((contacts > 0).sum())
    metrics["self_contacts"] = float(contacts.sum())
    return table, metrics
