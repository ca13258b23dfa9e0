"""Sign-like SMPL-X sequences: keyframes per sign (place, handshape, movement), arms solved by
IK, joint-space PCHIP interpolation for coarticulated transitions, then artifacts.

Everything random comes from one PCG64 stream per (seed, index), so files are reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.interpolate import PchipInterpolator

from embody.motion import LEFT_HAND, RIGHT_HAND, Motion, MotionSource
from embody.synth import artifacts, space
from embody.synth.handshapes import HANDSHAPES, MIRROR, handshape
from embody.synth.kinematics import SHOULDER_PRIOR, ArmIK
from embody.synth.lexicon import LEXICON, Sign

GENERATOR_VERSION = "embody-synth-2"
FPS = 30.0
MIN_FRAMES, MAX_FRAMES = 90, 180
SPINE, NECK, HEAD = 9, 12, 15
WRIST = {"left": 20, "right": 21}
SIDES = ("left", "right")


@dataclass
class Key:
    """One keyframe: wrist targets, finger poses and wrist rotations of both hands."""

    time: float
    targets: np.ndarray          # (2,3) left, right
    shapes: np.ndarray           # (2,15,3)
    wrists: np.ndarray           # (2,3) local wrist axis-angle
    sign: int = -1               # index into the sequence's signs, -1 for rest/transitions
    #: (2,3) shoulder priors for the arm IK; None: the default elbow-down posture
    shoulders: np.ndarray | None = None


@dataclass
class Plan:
    keys: list[Key] = field(default_factory=list)
    signs: list[Sign] = field(default_factory=list)
    #: penetration artifacts: (kind, sign index, extra record fields)
    penetrations: list[tuple[str, int, dict[str, Any]]] = field(default_factory=list)


def _rng(seed: int, index: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, index])))


def _rest_key(time: float) -> Key:
    relaxed = np.stack([handshape("relaxed", s) for s in SIDES])
    return Key(time, np.stack([space.location("rest", s) for s in SIDES]), relaxed, np.zeros((2, 3)))


def _path(movement: str, rng: np.random.Generator) -> list[tuple[float, np.ndarray]]:
    """(fraction of the sign, offset from its place) for the dominant hand."""
    def direction() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    if movement == "hold":
        return [(0.0, np.zeros(3)), (1.0, 0.01 * direction())]
    if movement == "tap":
        out = np.array([0.0, 0.0, rng.uniform(0.04, 0.07)])
        return [(0.0, out), (0.5, np.zeros(3)), (1.0, out)]
    if movement == "line":
        v = rng.uniform(0.04, 0.08) * direction()
        return [(0.0, -v), (1.0, v)]
    if movement == "repeat":
        v = rng.uniform(0.03, 0.06) * direction()
        return [(0.0, np.zeros(3)), (1 / 3, v), (2 / 3, np.zeros(3)), (1.0, v)]
    radius = rng.uniform(0.03, 0.06)
    phase = rng.uniform(0, 2 * np.pi)
    angles = phase + np.linspace(0, 2 * np.pi, 5)
    return [(i / 4, radius * np.array([np.cos(a), np.sin(a), 0.0])) for i, a in enumerate(angles)]


def _nondominant(sign: Sign, right: np.ndarray, place: np.ndarray) -> np.ndarray:
    """Left-wrist target for one keyframe of a sign, given the right one."""
    if sign.hands == "mirror":
        return right * np.array([-1.0, 1.0, 1.0])
    if sign.hands == "base":  # a still base hand below and across from the dominant place
        return np.array([0.10, max(place[1] - 0.14, -0.28), place[2] - 0.02])
    if sign.hands == "contact":  # hands approach each other and stop about a hand apart
        return np.array([right[0] + 0.18, right[1], right[2]])
    return space.location("rest", "left")


def _shoulders(sign: Sign) -> np.ndarray | None:
    """Shoulder priors (2,3) for the dominant arm at a place that needs its own posture."""
    prior = space.SHOULDER_PRIORS.get(sign.location)
    if prior is None:
        return None
    return np.stack([SHOULDER_PRIOR["left"], np.asarray(prior, dtype=np.float64)])


def plan_sequence(rng: np.random.Generator, signs: list[Sign] | None = None) -> Plan:
    """Choose signs, artifacts and keyframes (times in unscaled frames). Given `signs`, those
    are signed, without artifacts (e.g. one sequence per lexicon location)."""
    plan = Plan()
    if signs is None:
        n_signs = int(rng.integers(3, 7))
        plan.signs = [LEXICON[i] for i in rng.choice(len(LEXICON), n_signs, replace=False)]
    else:
        plan.signs, n_signs = list(signs), len(signs)
    inject: dict[int, str] = {}
    if signs is None and rng.random() >= 0.15:  # most sequences get 1-2 penetrations, a few stay clean
        kinds = rng.choice(artifacts.PENETRATIONS, size=int(rng.integers(1, 3)), replace=False)
        where = rng.choice(n_signs, size=len(kinds), replace=False)
        inject = {int(j): str(kind) for kind, j in zip(kinds, where)}

    plan.keys.append(_rest_key(0.0))
    t = float(rng.uniform(8, 14))
    for j, sign in enumerate(plan.signs):
        t += float(rng.uniform(8, 14))
        duration = float(rng.uniform(14, 24))
        place = space.location(sign.location, "right")
        end_shape = sign.handshape if rng.random() < 0.7 else str(rng.choice(HANDSHAPES))
        wrist = rng.uniform(-0.5, 0.5, size=3)
        wrists = np.stack([wrist * (MIRROR if sign.hands == "mirror" else rng.uniform(0.2, 0.6)), wrist])
        if j not in inject and sign.location in space.WRIST_TURNS:  # a hand that lies on the body
            turn, spread = space.WRIST_TURNS[sign.location]
            wrists[1] = np.asarray(turn) + spread * wrist
        path = _path(sign.movement, rng)
        pen_targets: np.ndarray | None = None
        if j in inject:
            kind = inject[j]
            if kind == "hand_hand":
                pen_targets, info = artifacts.hand_hand_targets(rng)
            else:
                target, info = (artifacts.torso_target if kind == "hand_torso" else artifacts.face_target)(rng)
                pen_targets = np.stack([space.location("rest", "left"), target])
            plan.penetrations.append((kind, j, info))
        for frac, offset in path:
            right = place + offset
            targets = np.stack([_nondominant(sign, right, place), right])
            if pen_targets is not None:  # keep the sign's movement, shrunk, around the bad place
                targets = pen_targets + 0.2 * offset
            shape = sign.handshape if frac < 1.0 else end_shape
            base = sign.base_shape if sign.hands != "one" else "relaxed"
            shapes = np.stack([handshape(base, "left"), handshape(shape, "right")])
            plan.keys.append(Key(t + frac * duration, targets, shapes, wrists.copy(), sign=j,
                                 shoulders=_shoulders(sign) if pen_targets is None else None))
        t += duration
    t += float(rng.uniform(8, 14))
    plan.keys.append(_rest_key(t))
    plan.keys.append(_rest_key(t + float(rng.uniform(4, 8))))
    return plan


def _key_poses(plan: Plan, rng: np.random.Generator, ik: ArmIK) -> tuple[np.ndarray, float]:
    """Full keyframe poses (K,55,3): posture noise, hands, wrists, then IK for the arms;
    and the worst wrist miss (m)."""
    k = len(plan.keys)
    pose = np.zeros((k, 55, 3))
    pose[:, SPINE] = rng.normal(0.0, 0.03, size=(k, 3))
    pose[:, NECK] = rng.normal(0.0, 0.05, size=(k, 3))
    pose[:, HEAD] = rng.normal(0.0, 0.07, size=(k, 3))
    for i, key in enumerate(plan.keys):
        pose[i, LEFT_HAND], pose[i, RIGHT_HAND] = key.shapes
        pose[i, WRIST["left"]], pose[i, WRIST["right"]] = key.wrists
    shoulders = None
    if any(key.shoulders is not None for key in plan.keys):
        default = np.stack([SHOULDER_PRIOR["left"], SHOULDER_PRIOR["right"]])
        shoulders = np.stack([default if key.shoulders is None else key.shoulders for key in plan.keys])
    solved, err = ik.solve(pose, np.stack([key.targets for key in plan.keys]), shoulders=shoulders)
    return solved, float(err.max())


def generate_sequence(seed: int, index: int, ik: ArmIK | None = None,
                      signs: list[Sign] | None = None) -> Motion:
    """One synthetic signing sequence (absolute hands, y-up, 30 fps) with its artifact record.

    Its metadata records each sign's ground truth: frames, lexicon location (where the dominant
    hand is placed) and two-handedness (`contact`: the hands meet)."""
    rng = _rng(seed, index)
    ik = ik or ArmIK()
    plan = plan_sequence(rng, signs)
    raw_end = plan.keys[-1].time
    frames = int(np.clip(round(raw_end * rng.uniform(0.8, 1.1)), MIN_FRAMES, MAX_FRAMES))
    scale = (frames - 1) / raw_end
    times = np.array([key.time for key in plan.keys]) * scale
    key_pose, ik_error = _key_poses(plan, rng, ik)
    pose = PchipInterpolator(times, key_pose.reshape(len(times), -1), axis=0)(np.arange(frames))
    pose = pose.reshape(frames, 55, 3)

    def window(j: int) -> tuple[int, int]:
        ts = [times[i] for i, key in enumerate(plan.keys) if key.sign == j]
        return int(np.floor(min(ts))), min(int(np.ceil(max(ts))) + 1, frames)

    records: list[dict[str, Any]] = []
    for kind, j, info in plan.penetrations:
        start, end = window(j)
        records.append({"kind": kind, "start": start, "end": end, **info})
    if plan.penetrations and rng.random() < 0.35:
        records.append(artifacts.inject_finger_overlap(pose, rng))
    if rng.random() < 0.4:
        records.append(artifacts.inject_jitter(pose, rng))
    records.sort(key=lambda r: (r["start"], r["kind"]))
    gloss = [sign.gloss for sign in plan.signs]
    meta = {
        "text": " ".join(gloss), "gloss": gloss, "artifacts": records,
        "signs": [{"gloss": s.gloss, "start": window(j)[0], "end": window(j)[1], "hands": s.hands,
                   "location": s.location, "handshape": s.handshape, "movement": s.movement,
                   "contact": "hands" if s.hands == "contact" else ""}
                  for j, s in enumerate(plan.signs)],
        "seed": seed, "index": index, "generator": GENERATOR_VERSION,
        "ik_error_max_m": round(ik_error, 5),
    }
    return Motion(pose=pose, transl=np.zeros((frames, 3)), betas=np.zeros(10), fps=FPS,
                  source=MotionSource("", "synth", "absolute"), meta=meta)
