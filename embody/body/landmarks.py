"""Named body landmarks (face, torso, hands) that move with the pose, on either body backend.

A sign is placed relative to the face and body (chin, cheek, forehead, chest...), so fidelity is
measured and retargeted against named surface points, not joints. Each landmark is a **mesh
vertex** of the body, chosen once per backend by the rule table `RULES` below (the vertices a
joint dominates by skinning weight, the support point in a direction, optionally limited to a
band), then carried by that vertex's own skinning weights (linear blend skinning, without SMPL-X's pose
correctives): at rest it lies exactly on the mesh.
The resulting table (name → joint, vertex id) is `BodyLandmarks.table()`, one per backend.

Directions in the rules are (forward, left, up); the body is y-up with +z forward and +x the
body's left (SMPL-X), so (f, l, u) maps to body (l, u, f). The palm normal is a direction, not a
point: the wrist frame's rotation applied to the rest palm normal (palms face down in the T-pose).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import torch

from embody.body.base import BodyModel

SIDES = ("left", "right")
FINGERS = ("thumb", "index", "middle", "ring", "pinky")
#: Landmarks of the face and trunk (where a sign is located).
BODY_LANDMARKS = ("head_top", "forehead", "left_eye", "right_eye", "nose", "mouth", "chin",
                  "left_cheek", "right_cheek", "throat", "left_shoulder", "right_shoulder",
                  "sternum", "belly", "left_hip", "right_hip")
FACE_LANDMARKS = BODY_LANDMARKS[:9]
#: Per hand: wrist, palm centre and the five fingertips.
HAND_LANDMARKS = tuple(f"{s}_{n}" for s in SIDES
                       for n in ("wrist", "palm", *(f"{f}_tip" for f in FINGERS)))
LANDMARKS = BODY_LANDMARKS + HAND_LANDMARKS
#: Landmarks carried rigidly by a trunk joint instead of their vertex's skinning weights: the
#: shoulder-top vertex is skinned to the arm, and with the arm down it swings ~7 cm out and back
#: (shoulder width 1.45x the rest width), while the robot's shoulder stays put; a sign "at the
#: shoulder" is placed on the trunk. At rest the landmark is still exactly its vertex.
CARRIED_BY = {"left_shoulder": "left_collar", "right_shoulder": "right_collar"}
#: Palm normal at rest (T-pose, palms down) in (forward, left, up).
PALM_NORMAL_REST = (0.0, 0.0, -1.0)


@dataclass(frozen=True)
class Rule:
    """Support vertex in `direction` among the vertices dominated by `joints`.

    `band`: (axis 0/1/2 of (f,l,u), anchor joint, half-width m): keep only vertices whose
    coordinate on that axis is within half-width of the anchor joint's (e.g. the midline).
    `near`: instead of a support point, the vertex closest to the anchor joint moved by
    `direction` (metres): used for the wrist and the palm centre. `along`: the support point
    along a bone (a fingertip is the farthest vertex of the distal segment along it).
    """

    joints: tuple[str, ...]
    direction: tuple[float, float, float]
    band: tuple[int, str, float] | None = None
    near: str | None = None
    #: (from joint, to joint): support along that bone instead of `direction` (fingertips).
    along: tuple[str, str] | None = None


_FACE = ("head", "jaw", "left_eye", "right_eye")
RULES: dict[str, Rule] = {
    "head_top": Rule(_FACE, (0.0, 0.0, 1.0)),
    "forehead": Rule(_FACE, (0.87, 0.0, 0.5)),
    "left_eye": Rule(_FACE, (0.92, 0.3, 0.25)),
    "right_eye": Rule(_FACE, (0.92, -0.3, 0.25)),
    "nose": Rule(_FACE, (1.0, 0.0, 0.0)),
    "mouth": Rule(_FACE, (0.95, 0.0, -0.3)),
    "chin": Rule(_FACE, (0.6, 0.0, -0.8)),
    "left_cheek": Rule(_FACE, (0.7, 0.7, -0.15)),
    "right_cheek": Rule(_FACE, (0.7, -0.7, -0.15)),
    "throat": Rule(("neck",), (1.0, 0.0, 0.0), band=(1, "neck", 0.02)),
    "left_shoulder": Rule(("left_shoulder", "left_collar"), (0.0, 0.0, 1.0), band=(1, "left_shoulder", 0.02)),
    "right_shoulder": Rule(("right_shoulder", "right_collar"), (0.0, 0.0, 1.0),
                           band=(1, "right_shoulder", 0.02)),
    "sternum": Rule(("spine3",), (1.0, 0.0, 0.0), band=(1, "spine3", 0.02)),
    "belly": Rule(("spine1", "spine2"), (1.0, 0.0, 0.0), band=(1, "spine1", 0.02)),
    "left_hip": Rule(("pelvis", "left_hip"), (0.0, 1.0, 0.0), band=(2, "left_hip", 0.03)),
    "right_hip": Rule(("pelvis", "right_hip"), (0.0, -1.0, 0.0), band=(2, "right_hip", 0.03)),
}
for _s in SIDES:
    RULES[f"{_s}_wrist"] = Rule((f"{_s}_wrist",), (0.0, 0.0, 0.0), near=f"{_s}_wrist")
    RULES[f"{_s}_palm"] = Rule((f"{_s}_wrist",), (0.0, 0.0, -0.05), near=f"{_s}_palm_mid")
    for _f in FINGERS:
        RULES[f"{_s}_{_f}_tip"] = Rule((f"{_s}_{_f}3",), (0.0, 0.0, 0.0), along=(f"{_s}_{_f}2", f"{_s}_{_f}3"))


def to_body_axes(v: np.ndarray) -> np.ndarray:
    """(forward, left, up) → body (x=left, y=up, z=forward)."""
    v = np.asarray(v, dtype=np.float64)
    return v[..., [1, 2, 0]]


@dataclass
class LandmarkSet:
    """Landmarks of one shaped body: per landmark its joint and offset in that joint's frame."""

    names: tuple[str, ...]
    vertex: np.ndarray  # (K,) mesh vertex ids
    joint: np.ndarray  # (K,) joint indices
    offset: np.ndarray  # (K,J,3) in each joint's frame
    weight: np.ndarray  # (K,J) skinning weights of the landmark vertex
    normal_joint: np.ndarray  # (2,) wrist joints [left, right]
    normal_local: np.ndarray  # (2,3) palm normals in the wrist frames
    scale: float  # shoulder-landmark distance at rest (m)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def table(self) -> dict[str, tuple[int, int]]:
        """name → (joint index, vertex id): the backend's landmark table."""
        return {n: (int(j), int(v)) for n, j, v in zip(self.names, self.joint, self.vertex)}

    def positions(self, transforms: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Landmark positions (T,K,3) and palm normals (T,2,3) from joint transforms (T,J,4,4)."""
        t = transforms.detach().cpu().numpy() if isinstance(transforms, torch.Tensor) else transforms
        t = np.asarray(t, dtype=np.float64)
        # Σ_j w_kj (p_j + R_j o_kj) over the few joints that skin each landmark (1-3 of 55): the
        # dense (T,K,J,3) einsum of every joint took ~97 % of the time (7 ms for 30 frames);
        # the same products, summed in the same (ascending joint) order: the same bits (tested)
        k, j = np.nonzero(self.weight)  # by landmark, then joint
        tj = t[:, j]
        per_pair = tj[..., :3, 3] + np.einsum("tpab,pb->tpa", tj[..., :3, :3], self.offset[k, j])
        term = per_pair * self.weight[k, j][:, None]
        counts = np.bincount(k, minlength=len(self.names))
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        points = np.zeros((len(t), len(self.names), 3))
        for r in range(counts.max(initial=0)):
            has = np.flatnonzero(counts > r)
            points[:, has] = points[:, has] + term[:, first[has] + r]
        normals = np.einsum("tkab,kb->tka", t[:, self.normal_joint][..., :3, :3], self.normal_local)
        return points, normals


_LOCK = threading.Lock()
_VERTICES: dict[int, dict[str, int]] = {}
_SETS: dict[tuple[int, bytes], LandmarkSet] = {}


def _joint(body: BodyModel, name: str) -> int | None:
    return body.joint_names.index(name) if name in body.joint_names else None


def _choose_vertices(body: BodyModel) -> dict[str, int]:
    """Apply `RULES` to the body's mean-shape rest mesh: landmark → vertex id."""
    zero = torch.zeros(10, dtype=torch.float64)
    verts = body.rest_vertices(zero).numpy().astype(np.float64)
    joints = body.joints(torch.zeros(1, 55, 3, dtype=torch.float64), zero)[0].numpy()
    dominant = np.asarray(body.skin_weights).argmax(1)
    jpos = {n: joints[i] for i, n in enumerate(body.joint_names)}
    for s in SIDES:  # palm middle: between the wrist and the middle finger's base
        jpos[f"{s}_palm_mid"] = 0.5 * (jpos[f"{s}_wrist"] + jpos[f"{s}_middle1"])
    out: dict[str, int] = {}
    for name, rule in RULES.items():
        ids = [i for i in (_joint(body, j) for j in rule.joints) if i is not None]
        cand = np.flatnonzero(np.isin(dominant, ids))
        if len(cand) == 0:  # a joint dominating no vertex (coarse meshes): use the whole mesh
            cand = np.arange(len(verts))
        direction = to_body_axes(rule.direction)
        if rule.near is not None:
            target = jpos[rule.near] + direction
            out[name] = int(cand[np.argmin(np.linalg.norm(verts[cand] - target, axis=1))])
            continue
        if rule.band is not None:
            axis, anchor, half = rule.band
            baxis = int(np.argmax(to_body_axes(np.eye(3)[axis])))
            keep = np.abs(verts[cand, baxis] - jpos[anchor][baxis]) < half
            cand = cand[keep] if keep.any() else cand
        centre = verts[cand].mean(0)
        if rule.along is not None:
            direction = jpos[rule.along[1]] - jpos[rule.along[0]]
        d = direction / np.linalg.norm(direction)
        out[name] = int(cand[np.argmax((verts[cand] - centre) @ d)])
    return out


def body_landmarks(body: BodyModel, betas: np.ndarray | torch.Tensor | None = None) -> LandmarkSet:
    """The landmark set of `body` shaped by `betas` (cached per body and betas)."""
    b = np.zeros(10) if betas is None else np.asarray(
        betas.detach().cpu().numpy() if isinstance(betas, torch.Tensor) else betas, dtype=np.float64)
    key = (id(body), b.astype(np.float32).tobytes())
    with _LOCK:
        if key in _SETS:
            return _SETS[key]
        if id(body) not in _VERTICES:
            _VERTICES[id(body)] = _choose_vertices(body)
        chosen = _VERTICES[id(body)]
    bt = torch.as_tensor(b, dtype=torch.float64)
    pose = torch.zeros(1, 55, 3, dtype=torch.float64)
    with torch.no_grad():
        verts = body.vertices(pose, bt)[0].numpy()
        rest = body.joint_transforms(pose, bt)[0].numpy()
    dominant = np.asarray(body.skin_weights).argmax(1)
    names = tuple(LANDMARKS)
    vertex = np.array([chosen[n] for n in names], dtype=np.int64)
    joint = dominant[vertex].astype(np.int64)
    rot, pos = rest[:, :3, :3], rest[:, :3, 3]
    offset = np.einsum("jba,kjb->kja", rot, verts[vertex][:, None] - pos[None])
    weight = np.asarray(body.skin_weights, dtype=np.float64)[vertex]
    weight = weight / weight.sum(1, keepdims=True)
    for name, carrier in CARRIED_BY.items():
        j = _joint(body, carrier)
        if j is not None:
            weight[names.index(name)] = np.eye(weight.shape[1])[j]
    wrists = np.array([body.joint_index(f"{s}_wrist") for s in SIDES], dtype=np.int64)
    normal = to_body_axes(PALM_NORMAL_REST)
    normal_local = np.stack([rest[w, :3, :3].T @ normal for w in wrists])
    shoulders = verts[vertex[[names.index("left_shoulder"), names.index("right_shoulder")]]]
    out = LandmarkSet(names=names, vertex=vertex, joint=joint, offset=offset, weight=weight, normal_joint=wrists,
                      normal_local=normal_local, scale=float(np.linalg.norm(shoulders[0] - shoulders[1])))
    with _LOCK:
        _SETS[key] = out
    return out


def landmark_positions(body: BodyModel, pose: np.ndarray | torch.Tensor, betas: np.ndarray | torch.Tensor,
                       transl: np.ndarray | torch.Tensor | None = None
                       ) -> tuple[np.ndarray, np.ndarray, LandmarkSet]:
    """Landmarks (T,K,3) and palm normals (T,2,3) of a posed body (body frame, y-up), and the set."""
    lm = body_landmarks(body, betas)
    p = torch.as_tensor(np.asarray(pose), dtype=torch.float64)
    tr = None if transl is None else torch.as_tensor(np.asarray(transl), dtype=torch.float64)
    with torch.no_grad():
        transforms = body.joint_transforms(p, torch.as_tensor(np.asarray(betas), dtype=torch.float64), tr)
    points, normals = lm.positions(transforms)
    return points, normals, lm
