"""Fidelity `Track`s of the two embodiments: the human body (landmarks + mesh contacts) and the
robot (YAML landmarks + MuJoCo geom distances), each on its own body and in its own torso frame.

Human contacts are closest distances between the skinned mesh's vertex sets (hand, face, chest,
by dominant skinning joint; a KD-tree per frame). Robot contacts are MuJoCo's own
`mj_geomDistance` between collision geoms: the hand's geoms (the wrist landmark body's subtree,
near the palm), the face's (the geoms closest to the face landmarks) and the chest's (closest to
sternum and belly), with its false 0.0 readings of separated meshes (MuJoCo #3383) recomputed
(`embody.metrics.convex_distance`). A negative distance is a penetration.
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections import OrderedDict
from dataclasses import replace
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import torch
from scipy.spatial import cKDTree

from embody.body.base import BodyModel
from embody.body.landmarks import LANDMARKS, body_landmarks
from embody.metrics.convex_distance import geom_distance
from embody.metrics.fidelity import CONTACTS, SIDES, Track, robot_contact_eps
from embody.motion import Motion
from embody.robot import Robot

if TYPE_CHECKING:
    from embody.config.fidelity import FidelityConfig

#: Body (x=left, y=up, z=forward) → (forward, left, up).
BODY_TO_FLU = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_FACE_JOINTS = ("head", "jaw", "left_eye", "right_eye")
_CHEST_JOINTS = ("spine2", "spine3")
_FACE_LANDMARKS = ("forehead", "nose", "mouth", "chin", "left_cheek", "right_cheek")
_CHEST_LANDMARKS = ("sternum", "belly")
#: Distances beyond this (m) are reported as this: only near contact matters.
_REACH = 0.05
#: Frames skinned at once for the human contacts (memory bound).
_CHUNK = 64


def _hand_joints(body: BodyModel, side: str) -> list[str]:
    return [n for n in body.joint_names if n.startswith(f"{side}_") and
            (n.endswith(("wrist", "hand")) or any(f in n for f in ("thumb", "index", "middle", "ring", "pinky")))]


def _vertex_sets(body: BodyModel) -> dict[str, np.ndarray]:
    dominant = np.asarray(body.skin_weights).argmax(1)

    def verts(joints) -> np.ndarray:
        ids = [body.joint_names.index(j) for j in joints if j in body.joint_names]
        return np.flatnonzero(np.isin(dominant, ids))

    out = {f"{s}_hand": verts(_hand_joints(body, s)) for s in SIDES}
    out["face"], out["chest"] = verts(_FACE_JOINTS), verts(_CHEST_JOINTS)
    return out


class _SubsetSkin:
    """Linear blend skinning of a vertex subset (SMPL-X's pose correctives left out; exact for
    the mannequin): the contact measure needs only hands, face and chest every frame.

    v(t) = Σ_j w_j B_j(t) [v_rest; 1] with B_j = T_j(t) T_j(rest)⁻¹ (3×4) is linear in the
    bones, so it is one float64 product P @ M(t) of a per-vertex table P[v, (j,b)] =
    w_vj·[v_rest; 1]_b (fixed per body and shape) and the frames' bones M[(j,b), (t,a)] =
    B_j(t)[a, b]. Why: the float32 blend of (V,J)@(T,J,12) then an einsum took 0.3-0.6 s per
    64 frames here (numpy's broadcast matmul), 1.7 s of every sequence's target build; this
    is ~15 ms, and float64 throughout."""

    def __init__(self, body: BodyModel, betas: np.ndarray, vertices: np.ndarray) -> None:
        b = torch.as_tensor(np.asarray(betas), dtype=torch.float64)
        zero = torch.zeros(1, 55, 3, dtype=torch.float64)
        with torch.no_grad():
            rest = body.vertices(zero, b)[0].numpy()[vertices]
            inv_rest = np.linalg.inv(body.joint_transforms(zero, b)[0].numpy())
        weight = np.asarray(body.skin_weights, dtype=np.float64)[vertices]
        self.joints = np.flatnonzero(weight.any(0))  # the joints these vertices follow
        self.inv_rest = inv_rest[self.joints]
        rest_h = np.concatenate([rest, np.ones((len(rest), 1))], 1)
        self.table = (weight[:, self.joints, None] * rest_h[:, None, :]).reshape(len(rest), -1)  # (V, 4J)

    def __call__(self, transforms: np.ndarray) -> np.ndarray:
        """(T,J,4,4) → (T,V,3)."""
        t = len(transforms)
        bone = (transforms[:, self.joints] @ self.inv_rest)[..., :3, :]          # (T,J,3,4)
        m = np.ascontiguousarray(bone.transpose(1, 3, 0, 2)).reshape(-1, t * 3)  # ((j,b), (t,a))
        return (self.table @ m).reshape(-1, t, 3).transpose(1, 0, 2)


#: Per body, per shape (betas bytes): the contact parts' slices and their `_SubsetSkin`.
_SKINS: weakref.WeakKeyDictionary[BodyModel, dict[bytes, tuple[dict[str, slice], _SubsetSkin]]] = \
    weakref.WeakKeyDictionary()
_SKINS_LOCK = threading.Lock()
#: Shapes remembered per body (a run has one per sequence at most).
_SKINS_SIZE = 8


def _contact_skin(body: BodyModel, betas: np.ndarray) -> tuple[dict[str, slice], _SubsetSkin]:
    """The parts' slices of the skinned subset and its `_SubsetSkin`, made once per body and
    shape. Why: making them (the shaped rest mesh, its joint transforms, the weight table) took
    ~20 ms, and each sequence asks twice with the same shape (the targets' hand gaps and the
    metrics step's human track); it is the same table every time."""
    key = np.asarray(betas, dtype=np.float64).tobytes()
    with _SKINS_LOCK:
        made = _SKINS.get(body, {}).get(key)
    if made is not None:
        return made
    sets = _vertex_sets(body)
    order = list(sets)
    allv = np.concatenate([sets[k] for k in order])
    bounds = np.cumsum([0] + [len(sets[k]) for k in order])
    made = ({k: slice(bounds[i], bounds[i + 1]) for i, k in enumerate(order)},
            _SubsetSkin(body, betas, allv))
    with _SKINS_LOCK:
        shapes = _SKINS.setdefault(body, {})
        shapes[key] = made
        while len(shapes) > _SKINS_SIZE:
            shapes.pop(next(iter(shapes)))
    return made


#: Per body: the latest sequences' `human_contacts` (every channel), by transforms and shape.
_CONTACTS_MEMO: weakref.WeakKeyDictionary[BodyModel, OrderedDict[bytes, np.ndarray]] = \
    weakref.WeakKeyDictionary()
_CONTACTS_LOCK = threading.Lock()
#: Sequences remembered per body: more than a run keeps in flight (the retarget step's targets
#: ask first, the same sequence's metrics step later, other batches' steps in between).
_CONTACTS_SIZE = 64


def human_contacts(body: BodyModel, transforms: np.ndarray, betas: np.ndarray,
                   channels: tuple[str, ...] = CONTACTS) -> np.ndarray:
    """Closest mesh distances (T, len(channels)) between hands, face and chest (m), from the
    body's joint transforms (T,J,4,4); `channels` a subset of CONTACTS, in that order.

    Remembered per body, transforms and shape (each channel is measured on its own, so any
    subset or order is columns of the same table): the retarget step's hand gaps and the metrics
    step's human track ask for the same sequence's (`rootless_transforms`), ~0.1 CPU-s each."""
    t = np.ascontiguousarray(transforms, dtype=np.float64)
    b = np.asarray(betas, dtype=np.float64)
    key = hashlib.blake2b(t.tobytes() + str(t.shape).encode() + b.tobytes(), digest_size=16).digest()
    with _CONTACTS_LOCK:
        full = _CONTACTS_MEMO.get(body, {}).get(key)
    if full is None:
        full = _human_contacts(body, t, b)
        with _CONTACTS_LOCK:
            memo = _CONTACTS_MEMO.setdefault(body, OrderedDict())
            memo[key] = full
            while len(memo) > _CONTACTS_SIZE:
                memo.popitem(last=False)
    return full[:, [CONTACTS.index(c) for c in channels]]  # a copy (fancy indexing)


def rootless_transforms(motion: Motion, body: BodyModel) -> np.ndarray:
    """The human's joint transforms (T,J,4,4) on its own shape, relative to its pelvis (root
    rotation and translation left out): where the targets see it, and where the contacts are
    measured (mesh distances do not change with the root)."""
    pose = torch.as_tensor(motion.pose, dtype=torch.float64).clone()
    pose[:, 0] = 0.0
    betas = np.asarray(motion.betas, dtype=np.float64)
    with torch.no_grad():
        return body.joint_transforms(pose, torch.as_tensor(betas)).numpy()


def _human_contacts(body: BodyModel, transforms: np.ndarray, betas: np.ndarray,
                    channels: tuple[str, ...] = CONTACTS) -> np.ndarray:
    """`human_contacts`' measure."""
    part, skin = _contact_skin(body, betas)
    pairs = {"hands": ("left_hand", "right_hand"), "left_face": ("left_hand", "face"),
             "right_face": ("right_hand", "face"), "left_chest": ("left_hand", "chest"),
             "right_chest": ("right_hand", "chest")}
    out = np.zeros((len(transforms), len(channels)))
    live = []  # (channel, hand part, other part) of the channels whose parts have vertices
    for c, name in enumerate(channels):
        if any(part[p].stop == part[p].start for p in pairs[name]):
            out[:, c] = np.nan
        else:
            live.append((c, *pairs[name]))
    for start in range(0, len(transforms), _CHUNK):
        verts = skin(np.asarray(transforms[start:start + _CHUNK], dtype=np.float64))
        # Broad phase for the whole chunk at once (the same comparisons the per-frame test made):
        # only hand points inside the other part's box grown by the reach count; a frame with
        # none is at least `_REACH` apart without building a tree.
        # Points are tested only on frames where the hand's own box meets that grown box (a
        # point inside it lies in both boxes, so the other frames have none).
        boxes = {p: (verts[:, part[p]].min(1) - _REACH, verts[:, part[p]].max(1) + _REACH)
                 for p in {b for _, _, b in live}}
        hands = {a: (verts[:, part[a]].min(1), verts[:, part[a]].max(1)) for _, a, _ in live}
        near = {}
        for c, a, b in live:
            (lo, hi), (h_lo, h_hi) = boxes[b], hands[a]
            meet = np.flatnonzero(((h_hi > lo) & (h_lo < hi)).all(-1))
            near[c] = np.zeros((len(verts), part[a].stop - part[a].start), dtype=bool)  # (T, hand points)
            va = verts[meet, part[a]]
            near[c][meet] = ((va > lo[meet, None]) & (va < hi[meet, None])).all(-1)
            out[start:start + len(verts), c] = np.where(near[c].any(1), np.nan, _REACH)
        for t, v in enumerate(verts):
            for c, a, b in live:
                if not near[c][t].any():
                    continue
                # The few hand points near the other part go in the tree, and only that part's
                # points within reach of their box are queried: the same pairs within reach,
                # each distance the same |a - b|, so the same least distance.
                va = v[part[a]][near[c][t]]
                vb = v[part[b]]
                vb = vb[((vb > va.min(0) - _REACH) & (vb < va.max(0) + _REACH)).all(1)]
                if len(vb) == 0:
                    out[start + t, c] = _REACH
                    continue
                d, _ = cKDTree(va).query(vb, k=1, distance_upper_bound=_REACH)
                out[start + t, c] = float(min(d.min(), _REACH))
    return out


def human_track(motion: Motion, body: BodyModel, with_contacts: bool = True) -> Track:
    """The human's landmarks, palm normals, torso frame and contacts, on its own shape."""
    betas = np.asarray(motion.betas, dtype=np.float64)
    lm = body_landmarks(body, betas)
    pose = torch.as_tensor(np.asarray(motion.pose), dtype=torch.float64)
    transl = None if motion.transl is None else torch.as_tensor(np.asarray(motion.transl), dtype=torch.float64)
    with torch.no_grad():
        transforms = body.joint_transforms(pose, torch.as_tensor(betas), transl).numpy()
        rest_t = body.joint_transforms(torch.zeros(1, 55, 3, dtype=torch.float64), torch.as_tensor(betas)).numpy()
    points, normals = lm.positions(transforms)
    rest, _ = lm.positions(rest_t)
    a = BODY_TO_FLU
    spine = transforms[:, body.joint_index("spine3"), :3, :3]
    torso = a @ spine @ a.T
    contact = human_contacts(body, rootless_transforms(motion, body), betas) if with_contacts else None
    return Track(names=tuple(LANDMARKS), points=points @ a.T, normals=normals @ a.T, torso=torso,
                 scale=lm.scale, rest=rest[0] @ a.T, contact=contact, fps=float(motion.fps))


def _geom_surface_distance(model: mujoco.MjModel, data: mujoco.MjData, g: int, p: np.ndarray) -> float:
    """Rough distance of a point to a geom (mesh: nearest vertex; primitives: centre − size)."""
    pos, rot = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        v = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        return float(np.linalg.norm(v @ rot.T + pos - p, axis=1).min())
    return float(max(np.linalg.norm(p - pos) - model.geom_size[g].max(), 0.0))


class RobotContactGeoms:
    """The robot's collision geoms per contact channel (hands, face, chest), found at the T-pose."""

    def __init__(self, robot: Robot) -> None:
        m = robot.model
        d = mujoco.MjData(m)
        d.qpos[:] = robot.qpos(robot.tpose)
        mujoco.mj_kinematics(m, d)
        world = np.linalg.inv(robot.torso_from_world)
        pts, _, names = robot.landmark_points(robot.tpose[None])
        at = {n: world[:3, :3] @ pts[0, i] + world[:3, 3] for i, n in enumerate(names)}
        groups = list(robot.spec.collision.geom_groups)
        coll = [g for g in range(m.ngeom) if m.geom_group[g] in groups]

        def closest(lnames) -> list[int]:
            out = set()
            for n in lnames:
                if n not in at:
                    continue
                body = m.body(robot.spec.landmarks[n].body).id
                cand = [g for g in coll if m.geom_bodyid[g] == body] or coll
                out.add(min(cand, key=lambda g: _geom_surface_distance(m, d, g, at[n])))
            return sorted(out)

        from embody.robot.contacts import subtree_ids
        self.sets: dict[str, list[int]] = {"face": closest(_FACE_LANDMARKS), "chest": closest(_CHEST_LANDMARKS)}
        for s in SIDES:
            wrist = robot.spec.landmarks[f"{s}_wrist"].body
            sub = subtree_ids(m, wrist)
            palm = at[f"{s}_palm"]
            self.sets[f"{s}_hand"] = [g for g in coll if m.geom_bodyid[g] in sub and (
                m.geom_bodyid[g] != m.body(wrist).id or np.linalg.norm(d.geom_xpos[g] - palm) < 0.12)]
        self.pairs = {"hands": ("left_hand", "right_hand"), "left_face": ("left_hand", "face"),
                      "right_face": ("right_hand", "face"), "left_chest": ("left_hand", "chest"),
                      "right_chest": ("right_hand", "chest")}


#: Safety margin (m) of `robot_contacts`' broad phase: a pair whose bounding spheres are more
#: than `distmax` plus this apart is not measured (MuJoCo would read `distmax` for it).
_BROAD_MARGIN = 0.01


def _contact_geoms(robot: Robot) -> RobotContactGeoms:
    """`RobotContactGeoms` of `robot`, found once per robot object (~10 ms each time)."""
    geoms = getattr(robot, "_contact_geoms", None)
    if geoms is None:
        geoms = RobotContactGeoms(robot)
        robot._contact_geoms = geoms  # type: ignore[attr-defined]
    return geoms


def robot_contacts(robot: Robot, q: np.ndarray, distmax: float = 0.1) -> np.ndarray:
    """MuJoCo's closest signed distances (T, len(CONTACTS)) per channel (m; < 0 penetrates),
    checked by `geom_distance` where MuJoCo claims a touch.

    Per frame and channel this is `closest_pair` over the channel's geom pairs, in its order,
    leaving out the pairs whose bounding spheres (`geom_rbound`) are more than `distmax` +
    `_BROAD_MARGIN` apart: MuJoCo reads exactly `distmax` for those, which never lowers the
    least distance, so the result is the same bit for bit (tested against all pairs). Why: of
    the ~117 pairs a frame, most are hands far from each other and from the face, and each
    `geom_distance` call is a few microseconds of Python and MuJoCo."""
    geoms = _contact_geoms(robot)
    m = robot.model
    d = mujoco.MjData(m)
    q = np.asarray(q, dtype=np.float64)
    out = np.full((len(q), len(CONTACTS)), distmax)
    pairs = [(c, ga, gb) for c, name in enumerate(CONTACTS)
             for ga in geoms.sets[geoms.pairs[name][0]] for gb in geoms.sets[geoms.pairs[name][1]]]
    if not pairs or not len(q):
        return out
    channel, pa, pb = (np.array(v) for v in zip(*pairs))
    radii = m.geom_rbound[pa] + m.geom_rbound[pb]
    fromto = np.zeros(6)
    for t, qt in enumerate(q):
        d.qpos[:] = robot.qpos(qt)
        mujoco.mj_kinematics(m, d)
        centres = d.geom_xpos
        apart = np.linalg.norm(centres[pa] - centres[pb], axis=-1) - radii
        for p in np.flatnonzero(apart <= distmax + _BROAD_MARGIN):
            value = geom_distance(m, d, int(pa[p]), int(pb[p]), distmax, fromto)
            if value < out[t, channel[p]]:
                out[t, channel[p]] = value
    return out


def closest_pair(m: mujoco.MjModel, d: mujoco.MjData, geoms_a: list[int], geoms_b: list[int],
                 distmax: float) -> tuple[float, np.ndarray]:
    """The least `geom_distance` between two geom sets at `d`'s kinematics (`distmax` when none
    is nearer) and the closest points of that pair (6,) (from a to b; zeros when none is)."""
    fromto, best_fromto = np.zeros(6), np.zeros(6)
    best = distmax
    for ga in geoms_a:
        for gb in geoms_b:
            value = geom_distance(m, d, ga, gb, distmax, fromto)
            if value < best:
                best, best_fromto[:] = value, fromto
    return best, best_fromto


def robot_track(robot: Robot, q: np.ndarray, fps: float, with_contacts: bool = True) -> Track:
    """The robot's landmarks, palm normals, torso frame and MuJoCo contacts for joint values q."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    points, normals, names = robot.landmark_points(q)
    rest, _, _ = robot.landmark_points(robot.tpose[None])
    fk = robot.fk([robot.spec.torso_body])
    rot, _ = fk.forward(q)
    torso = rot[:, fk.index[robot.spec.torso_body]]
    return Track(names=tuple(names), points=points, normals=normals, torso=torso, scale=robot.body_scale,
                 rest=rest[0], contact=robot_contacts(robot, q) if with_contacts else None, fps=fps)


#: How far past the robot's contact ε `scored_robot_track` measures (m): any reach above ε gives
#: the same contact masks; this keeps the pairs it measures near that ε.
_SCORE_REACH = 0.005


def scored_robot_track(robot: Robot, q: np.ndarray, fps: float, human: Track,
                       cfg: FidelityConfig) -> Track:
    """`robot_track` with its contacts measured only as far as `compare_with` (a
    `FidelityConfig` `cfg`, against `human`) reads them: it reads a robot distance only against
    the robot's contact ε (and the penetration tolerance below 0), so every distance beyond
    ε + `_SCORE_REACH` reads as that (`robot_contacts`' `distmax`, at most its default 0.1):
    the same masks, hence the same scores. Why: the broad phase then drops the pairs 2-11 cm
    apart, most of those the default 0.1 m measured (~0.1 CPU-s of a sequence's metrics)."""
    track = robot_track(robot, q, fps, with_contacts=False)
    eps = cfg.robot_contact_eps if cfg.robot_contact_eps is not None else \
        robot_contact_eps(human, track, cfg.contact_eps)
    return replace(track, contact=robot_contacts(robot, np.atleast_2d(q), min(0.1, eps + _SCORE_REACH)))
