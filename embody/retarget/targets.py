"""Per-frame retargeting targets in the robot torso frame, built from the fitted body.

The body is evaluated with the fitted betas and its root rotation and translation removed, so
targets follow the signer's upper body relative to the pelvis, whatever the camera frame.
Positions map through the shape fit (p_robot = s·R·p_body + t).

Orientation offset (calibrated at the T-pose): in the SMPL-X zero pose every joint's global
rotation is the identity, so a human link rotated by G(t) (body frame) maps to the robot link
rotation  R · G(t) · Rᵀ · R_link^tpose , where R is the body→robot change of axes and
R_link^tpose the robot link's rotation at its T-pose (torso frame). At the T-pose the target is
exactly the robot's T-pose orientation: palms down on both.

Location-preserving wrist targets (`ik.location_preserving`): a sign is placed relative to the
face and body, and the shape fit alone does not keep that (robot and human proportions differ:
a G1 torso is much thinner, so hands land too far forward). Each human hand point the robot also
has (palm centre, thumb/index/middle tips) is expressed relative to each body landmark (chin,
cheek, forehead, sternum, ...) in the human torso frame and per human body scale; rescaled to the
robot's scale and added to the robot's landmark of the same name (torso-frame landmarks turn
with the tracked torso orientation, so targets are chest-relative, not pelvis-relative), it gives
where that hand point should be, hence (through the hand's own FK at the retargeted finger
angles) where the wrist should be. A soft-min over (point, landmark) pairs keeps this smooth as
the nearest landmark changes. The blend weight rises from 0 (`anchor_far` body scales away) to 1
(`anchor_near`): near the body the anchored target wins, far from it the shape-fit target stays.

Contact vs collision margin: an anchored touch aims the touching point at the robot's surface
(offset ≈ 0), while the self-collision term keeps `collision_margin` between proxies. We keep the
margin (no penetration, ever) and let it decide the last centimetre: the robot touches at the
margin (MuJoCo measures it at 1.3-1.7 cm between its hulls: the proxies are larger), and the
fidelity measure counts a robot contact within `fidelity.robot_contact_eps` (the human's ε at
hand scale) when it does not penetrate. Hand-hand: where the human's hands are apart the robot's
keep the human's gap at hand scale (`hand_gaps`, `embody.retarget.hand_clearance`), so hands
that only pass near each other do not touch on the robot's bigger hands.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.body.landmarks import LandmarkSet, body_landmarks
from embody.config.ik import IKConfig
from embody.motion import Motion
from embody.retarget.finger_clearance import clear_fingers
from embody.retarget.hands import fold_thumbs, rate_limit, retarget_hands
from embody.retarget.shape_fit import ShapeFit
from embody.robot import Robot

#: The root-free human of `_human`: joint transforms (T,J,4,4), betas, landmark table.
Human = tuple[np.ndarray, np.ndarray, LandmarkSet]

_ARRAYS = ("wrist_pos", "wrist_rot", "elbow_pos", "torso_rot", "head_rot", "hand_q", "point_pos", "point_weight",
           "wrist_weight", "wrist_rot_weight", "hand_gap")


@dataclass
class Targets:
    """wrist_pos (T,2,3) [left, right], wrist_rot (T,2,3,3), elbow_pos (T,2,3),
    torso_rot / head_rot (T,3,3), hand_q (T,H) for `hand_joints`, all in the robot torso frame;
    point_pos (T,P,3) / point_weight (T,P): anchored targets of the robot hand landmarks
    `point_names` (`embody.retarget.hand_points`; P = 0 without location preservation);
    wrist_weight (T,2): share of the wrist pose terms kept (1 − the anchored point weight ×
    `ik.touch_release`: at a touch the touching point, not the human's wrist position, decides);
    wrist_rot_weight (T,2): factor on the wrist orientation term (`ik.w_wrist_rot_touch` /
    `ik.w_wrist_rot` at a touch: the anchored points must not twist the palm);
    hand_gap (T,5): the least clearance (m) the robot must keep between its hands, and between
    each hand and its chest and face (`hand_clearance.CHANNELS`), 0 where the human's touch or with
    location preservation off (`embody.retarget.hand_clearance`)."""

    wrist_pos: np.ndarray
    wrist_rot: np.ndarray
    elbow_pos: np.ndarray
    torso_rot: np.ndarray
    head_rot: np.ndarray
    hand_q: np.ndarray
    hand_joints: list[str]
    fps: float
    #: Robot shoulder→elbow→wrist length (m), to normalise errors.
    arm_length: float
    point_pos: np.ndarray | None = None
    point_weight: np.ndarray | None = None
    point_names: list[str] = field(default_factory=list)
    wrist_weight: np.ndarray | None = None
    wrist_rot_weight: np.ndarray | None = None
    hand_gap: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = len(self.wrist_pos)
        if self.point_pos is None:
            self.point_pos = np.zeros((t, len(self.point_names), 3))
        if self.point_weight is None:
            self.point_weight = np.zeros((t, len(self.point_names)))
        if self.wrist_weight is None:
            self.wrist_weight = np.ones((t, 2))
        if self.wrist_rot_weight is None:
            self.wrist_rot_weight = np.ones((t, 2))
        if self.hand_gap is None:
            self.hand_gap = np.zeros((t, 5))

    @property
    def num_frames(self) -> int:
        return int(self.wrist_pos.shape[0])

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in _ARRAYS}

    def to_attrs(self) -> dict[str, Any]:
        return {"hand_joints": list(self.hand_joints), "fps": self.fps, "arm_length": self.arm_length,
                "point_names": list(self.point_names)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "Targets":
        return cls(**{k: np.asarray(arrays[k]) if k in arrays else None for k in _ARRAYS},
                   hand_joints=list(attrs["hand_joints"]), fps=float(attrs["fps"]),
                   arm_length=float(attrs["arm_length"]), point_names=list(attrs.get("point_names", [])))

    def with_wrists(self, wrist_pos: np.ndarray, wrist_rot: np.ndarray) -> "Targets":
        """These targets with new wrist poses; the hand-point targets move rigidly with their wrist
        (a critic's "move the right hand up" moves the anchored fingertip up too)."""
        point_pos = np.array(self.point_pos, dtype=np.float64, copy=True)
        for k, side in enumerate(("left", "right")):
            cols = [i for i, n in enumerate(self.point_names) if n.startswith(f"{side}_")]
            if cols:
                turn = np.asarray(wrist_rot)[:, k] @ np.swapaxes(np.asarray(self.wrist_rot)[:, k], -1, -2)
                rel = point_pos[:, cols] - np.asarray(self.wrist_pos)[:, k, None]
                point_pos[:, cols] = np.asarray(wrist_pos)[:, k, None] + np.einsum("tab,tpb->tpa", turn, rel)
        return replace(self, wrist_pos=np.asarray(wrist_pos), wrist_rot=np.asarray(wrist_rot), point_pos=point_pos)


def robot_arm_length(robot: Robot) -> float:
    q = torch.as_tensor(robot.tpose)[None]
    with torch.no_grad():
        p, _ = robot.link_points(q, ["left_shoulder", "left_elbow", "left_wrist"])
    p = p[0].numpy()
    return float(np.linalg.norm(p[1] - p[0]) + np.linalg.norm(p[2] - p[1]))


def tpose_rotations(robot: Robot, links: list[str]) -> np.ndarray:
    with torch.no_grad():
        _, r = robot.link_points(torch.as_tensor(robot.tpose)[None], links)
    return r[0].numpy()


#: Landmarks a hand is anchored to, and the hand points anchored (when the robot has them).
ANCHOR_LANDMARKS = ("forehead", "left_eye", "right_eye", "nose", "mouth", "chin", "left_cheek",
                    "right_cheek", "throat", "left_shoulder", "right_shoulder", "sternum", "belly")
HAND_POINTS = ("palm", "thumb_tip", "index_tip", "middle_tip")


def _torso_descendants(robot: Robot) -> set[str]:
    from embody.robot.contacts import subtree_ids
    ids = subtree_ids(robot.model, robot.spec.torso_body)
    return {robot.model.body(b).name for b in ids}


@dataclass
class Anchored:
    """Landmark-anchored targets in the torso frame: wrists (T,2,3) with blend weights (T,2), and
    the robot hand points `point_names` (T,P,3) with their weights (T,P) for `hand_points`."""

    wrist: np.ndarray
    weight: np.ndarray
    point_names: list[str]
    point_pos: np.ndarray
    point_weight: np.ndarray
    #: (T,P) how much each point touches its landmark (within `ik.touch_radius`), times its share
    point_touch: np.ndarray


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)  # no kink where anchoring starts


def anchored_targets(motion: Motion, body: BodyModel, fit: ShapeFit, robot: Robot, wrist_rot: np.ndarray,
                     torso_rot: np.ndarray, hand_q: np.ndarray, hand_joints: list[str],
                     cfg: IKConfig, human: Human | None = None) -> Anchored:
    """Landmark-anchored wrist and hand-point targets (see the module docstring).

    Hand points: each robot hand point's target is the soft-min over landmarks of (robot landmark
    + rescaled human offset), its offset lengthened to at least `cfg.touch_clearance` (a touch
    ends at the clearance the collision term keeps, see `hand_points`). Its share is
    exp(−(its distance − the nearest point's) / `cfg.hand_point_softness`): the point nearest the
    body (the touching fingertip) dominates, so the robot's other hand proportions do not pull it
    off. Its weight (relative to `w_hand_points`) is share × a touch smoothstep within
    `touch_radius` (the full pull at a touch, where the wrist terms are released instead), plus,
    for the palm, `w_hand_points_near` / `w_hand_points` × the anchoring smoothstep: the palm
    carries the sign's location (and anchors the wrist target), the other points its contacts."""
    t = motion.num_frames
    lm_names = [n for n in ANCHOR_LANDMARKS if n in robot.spec.landmarks]
    if not lm_names:
        return Anchored(np.zeros((t, 2, 3)), np.zeros((t, 2)), [], np.zeros((t, 0, 3)), np.zeros((t, 0)),
                        np.zeros((t, 0)))
    tr, betas, hl = human or _human(motion, body)
    hp, _ = hl.positions(tr)
    axes = fit.rotation
    hp = hp @ axes.T
    h_torso = axes @ tr[:, body.joint_index("spine3"), :3, :3] @ axes.T
    # the robot: landmarks at the T-pose, turned with the torso target where they ride on it
    q0 = np.tile(robot.tpose, (t, 1))
    if hand_joints:
        q0[:, [robot.joint_index(n) for n in hand_joints]] = hand_q
    rp, _, rnames = robot.landmark_points(robot.tpose[None], lm_names)
    on_torso = _torso_descendants(robot)
    r_lm = np.where(np.array([robot.spec.landmarks[n].body in on_torso for n in rnames])[None, :, None],
                    np.einsum("tab,kb->tka", torso_rot, rp[0]), rp[0][None])
    out, weight = np.zeros((t, 2, 3)), np.zeros((t, 2))
    s_h, s_r = hl.scale, robot.body_scale
    span = max(cfg.anchor_far - cfg.anchor_near, 1e-9)
    p_names: list[str] = []
    p_pos: list[np.ndarray] = []
    p_weight: list[np.ndarray] = []
    p_touch: list[np.ndarray] = []
    for k, side in enumerate(("left", "right")):
        points = [n for n in HAND_POINTS if f"{side}_{n}" in robot.spec.landmarks]
        # each hand point's offset from the wrist link point, in the wrist link's frame (finger FK)
        wp, wr = robot.link_poses(q0, [f"{side}_wrist"])
        tips, _, _ = robot.landmark_points(q0, [f"{side}_{n}" for n in points])
        local = np.einsum("tba,tpb->tpa", wr[:, 0], tips - wp)  # (T,P,3)
        human = np.stack([hp[:, hl.index(f"{side}_{n}")] for n in points], 1)  # (T,P,3)
        h_lm = np.stack([hp[:, hl.index(n)] for n in lm_names], 1)  # (T,L,3)
        rel = human[:, :, None] - h_lm[:, None]  # (T,P,L,3)
        dist = np.linalg.norm(rel, axis=-1) / s_h
        rel_local = np.einsum("tba,tplb->tpla", h_torso, rel) * (s_r / s_h)
        target_point = r_lm[:, None] + np.einsum("tab,tplb->tpla", torso_rot, rel_local)
        wrist = target_point - np.einsum("tab,tpb->tpa", wrist_rot[:, k], local)[:, :, None]
        dmin = dist.reshape(t, -1).min(1)
        # the wrist is anchored by the palm (a sign's location is the palm's; other hand points
        # carry touches, below): the robot's thumb sits elsewhere on its palm than a human's
        loc = [points.index("palm")] if "palm" in points else list(range(len(points)))
        dloc = dist[:, loc].reshape(t, -1).min(1)
        alpha = np.exp(-(dist[:, loc] - dloc[:, None, None]) / cfg.anchor_softness)
        alpha /= alpha.sum((1, 2), keepdims=True)
        out[:, k] = np.einsum("tpl,tpla->ta", alpha, wrist[:, loc])
        weight[:, k] = _smoothstep((cfg.anchor_far - dmin) / span)
        # hand points: a touch ends at the collision margin from the landmark, not inside it
        offset = np.einsum("tab,tplb->tpla", torso_rot, rel_local)
        length = np.linalg.norm(offset, axis=-1, keepdims=True)
        offset = offset * np.where(length > 1e-9, np.maximum(length, cfg.touch_clearance) / np.maximum(length, 1e-12), 1.0)
        beta = np.exp(-(dist - dist.min(2, keepdims=True)) / cfg.anchor_softness)
        beta /= beta.sum(2, keepdims=True)
        p_pos.append(np.einsum("tpl,tpla->tpa", beta, r_lm[:, None] + offset))
        dp = dist.min(2)  # (T,P)
        share = np.exp(-(dp - dmin[:, None]) / cfg.hand_point_softness)
        touch = share * _smoothstep((cfg.touch_radius - dp) / cfg.touch_radius)
        near = cfg.w_hand_points_near / max(cfg.w_hand_points, 1e-12)
        is_loc = np.isin(np.arange(len(points)), loc)[None]
        held = 1.0 - cfg.touch_release * touch.max(1, keepdims=True)  # a touch decides, not the palm
        p_weight.append(np.where(is_loc, _smoothstep((cfg.anchor_far - dp) / span) * near * held, 0.0)
                        + (1.0 - near) * touch)
        p_touch.append(touch)
        p_names += [f"{side}_{n}" for n in points]
    return Anchored(out, weight, p_names, np.concatenate(p_pos, 1), np.concatenate(p_weight, 1),
                    np.concatenate(p_touch, 1))


def _human(motion: Motion, body: BodyModel) -> Human:
    """The human on its own shape, relative to its pelvis (root rotation removed, as the targets
    are): joint transforms (T,J,4,4), its betas and its landmark table. `build_targets` makes it
    once and hands it to the anchoring, the thumb fold and the hand gaps."""
    from embody.metrics.embodiments import rootless_transforms
    betas = np.asarray(motion.betas, dtype=np.float64)
    return rootless_transforms(motion, body), betas, body_landmarks(body, betas)


def palm_rest(motion: Motion, body: BodyModel, robot: Robot, cfg: IKConfig,
              human: Human | None = None) -> np.ndarray:
    """(T,2) [left, right]: how much each human palm rests on the body, facing it, with a free
    thumb (`hands.palm_rest_weight`; distances to the nearest `ANCHOR_LANDMARKS` per body scale,
    within `cfg.touch_radius`): the weight `hands.fold_thumbs` lays the robot thumb down by."""
    from embody.retarget.hands import finger_curls, palm_rest_weight
    t = motion.num_frames
    lm_names = [n for n in ANCHOR_LANDMARKS if n in robot.spec.landmarks]
    if not lm_names or not robot.spec.hands:
        return np.zeros((t, 2))
    tr, _, hl = human or _human(motion, body)
    hp, normals = hl.positions(tr)
    lm = np.stack([hp[:, hl.index(n)] for n in lm_names], 1)  # (T,L,3)
    out = np.zeros((t, 2))
    for k, side in enumerate(("left", "right")):
        rel = lm - hp[:, hl.index(f"{side}_palm"), None]  # palm → landmark
        dist = np.linalg.norm(rel, axis=-1)
        near = dist.argmin(1)
        d = dist[np.arange(t), near]
        facing = np.einsum("ta,ta->t", normals[:, k], rel[np.arange(t), near]) / np.maximum(d, 1e-12)
        out[:, k] = palm_rest_weight(d / hl.scale, facing, finger_curls(np.asarray(motion.pose), side)
                                     ["thumb_opposition"], cfg.touch_radius)
    return out


#: The hand-face clearance asked (m, proxies) at most: enough that a hand passing near the face is
#: not a robot contact (`fidelity.robot_contact_eps` 2.1 cm on G1), not the full hand-scale gap
#: (`ik.hand_gap_max`): face signs are placed by landmark offsets at body scale, and a 5 cm
#: face clearance pushed hands near the chin off their landmark (location agreement 88 → 56 %
#: on synth sequence 8).
FACE_GAP_MAX = 0.025


def hand_gaps(motion: Motion, body: BodyModel, robot: Robot, cfg: IKConfig,
              human: Human | None = None) -> np.ndarray:
    """The robot's least clearance per frame (T,5) between its hands and between each hand and
    its chest and its face (`embody.retarget.hand_clearance.CHANNELS`): the human's mesh gap times the
    hand-size ratio, capped at `hand_gap_max`, where the human's are apart (gap >
    `hand_contact_eps`); 0 where they touch."""
    t = motion.num_frames
    if cfg.w_hand_clearance <= 0 or not all(f"{s}_wrist" in robot.spec.landmarks for s in ("left", "right")):
        return np.zeros((t, 5))
    from embody.metrics.embodiments import human_contacts  # the fidelity measure's own human gap
    from embody.retarget.hand_clearance import CHANNELS, hand_ratio

    tr, betas, hl = human or _human(motion, body)
    with torch.no_grad():
        rest = body.joint_transforms(torch.zeros(1, np.shape(motion.pose)[1], 3, dtype=torch.float64),
                                     torch.as_tensor(betas)).numpy()
    gap = human_contacts(body, tr, betas, CHANNELS)
    h_rest, _ = hl.positions(rest)
    r_rest, _, r_names = robot.landmark_points(robot.tpose[None])
    rho = hand_ratio(h_rest[0], hl.names, r_rest[0], r_names, robot.body_scale / hl.scale)
    gap = np.where(np.isfinite(gap), gap, 0.0)
    cap = np.array([FACE_GAP_MAX if c.endswith("_face") else cfg.hand_gap_max for c in CHANNELS])
    return np.where(gap > cfg.hand_contact_eps, np.minimum(rho * gap, cap), 0.0)


#: Rounds of finger rate limit then finger clearance (`build_targets`): each round's clearance
#: moves fewer frames, by less, so the next limit brings fewer back into contact.
RATE_CLEAR_ROUNDS = 3


def build_targets(motion: Motion, body: BodyModel, fit: ShapeFit, robot: Robot,
                  cfg: IKConfig | None = None) -> Targets:
    """Targets for every frame of `motion` (its hands must be absolute, as `Motion` guarantees).
    With `cfg.location_preserving` the wrist targets are blended towards landmark-anchored ones."""
    pose = torch.as_tensor(motion.pose, dtype=torch.float64).clone()
    pose[:, 0] = 0.0  # root rotation: targets are relative to the pelvis
    betas = torch.as_tensor(fit.betas, dtype=torch.float64)
    with torch.no_grad():
        transforms = body.joint_transforms(pose, betas)
    pos = fit.apply(transforms[..., :3, 3]).numpy()
    rot = transforms[..., :3, :3].numpy()
    axes = fit.rotation

    def idx(name: str) -> int:
        return body.joint_index(name)

    def mapped_rot(joint: str, link: str) -> np.ndarray:
        rest = tpose_rotations(robot, [link])[0]
        return axes @ rot[:, idx(joint)] @ axes.T @ rest

    sides = ("left", "right")
    identity = np.tile(np.eye(3), (len(pos), 1, 1))
    hand_q, hand_joints = retarget_hands(motion.pose, robot)
    wrist_pos = np.stack([pos[:, idx(f"{s}_wrist")] for s in sides], axis=1)
    wrist_rot = np.stack([mapped_rot(f"{s}_wrist", f"{s}_wrist") for s in sides], axis=1)
    torso_rot = mapped_rot("spine3", "spine3") if "spine3" in robot.spec.links else identity
    preserving = cfg is not None and cfg.location_preserving and bool(robot.spec.landmarks)
    if preserving:
        # a palm laid on the body: the robot thumb lies down too (`hands.fold_thumbs`)
        human = _human(motion, body)
        hand_q = fold_thumbs(hand_q, hand_joints, robot, palm_rest(motion, body, robot, cfg, human))
    clearance = cfg is not None and cfg.hand_self_clearance and bool(hand_joints)
    if clearance:
        # a handshape the hand can take: fingers stop where they meet (`finger_clearance`)
        hand_q = clear_fingers(robot, hand_q, hand_joints)
    if cfg is not None and cfg.hand_rate_limit and hand_joints:
        # fingers the robot can follow: the IK places the arms around the fingers it will get
        vmax = robot.velocity_limits[[robot.joint_index(n) for n in hand_joints]] * (1.0 - cfg.velocity_headroom)
        for _ in range(RATE_CLEAR_ROUNDS if clearance else 1):
            limited = rate_limit(hand_q, vmax, motion.fps)
            if clearance:
                # a finger slowed down on its way past another passes through it (synth seqs 0/5:
                # 15-18 frames up to 18 mm, which the contact repair then pushed apart at the
                # velocity limit, 5-10x the solve time): clear those frames, limit again (the
                # frames the limit left alone are clear already)
                limited = clear_fingers(robot, limited, hand_joints, cleared=hand_q)
            hand_q = limited
    if preserving:
        anchored = anchored_targets(motion, body, fit, robot, wrist_rot, torso_rot, hand_q, hand_joints, cfg,
                                    human)
        wrist_pos = wrist_pos + anchored.weight[..., None] * (anchored.wrist - wrist_pos)
        release, hold = np.ones((motion.num_frames, 2)), np.ones((motion.num_frames, 2))
        boost = cfg.w_wrist_rot_touch / cfg.w_wrist_rot if cfg.w_wrist_rot > 0 else 1.0
        for k, side in enumerate(("left", "right")):
            cols = [i for i, n in enumerate(anchored.point_names) if n.startswith(f"{side}_")]
            if cols and cfg.w_hand_points > 0:
                touch = anchored.point_touch[:, cols].max(1)
                release[:, k] -= cfg.touch_release * touch
                hold[:, k] += (boost - 1.0) * touch
        points = dict(point_pos=anchored.point_pos, point_weight=anchored.point_weight,
                      point_names=anchored.point_names, wrist_weight=release, wrist_rot_weight=hold,
                      hand_gap=hand_gaps(motion, body, robot, cfg, human))
    else:
        points = {}
    return Targets(
        wrist_pos=wrist_pos,
        wrist_rot=wrist_rot,
        elbow_pos=np.stack([pos[:, idx(f"{s}_elbow")] for s in sides], axis=1),
        torso_rot=torso_rot,
        head_rot=mapped_rot("head", "head") if "head" in robot.spec.links else identity,
        hand_q=hand_q, hand_joints=hand_joints, fps=motion.fps, arm_length=robot_arm_length(robot),
        **points,
    )
