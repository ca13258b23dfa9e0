"""Sign fidelity: does the robot sign what the human signed, each measured on its own body?

A sign is its handshape, location (relative to face and body), palm orientation, movement and
contacts. Both embodiments are reduced to a `Track` (named landmarks, palm normals, torso
orientation, body scale, contact distances) and compared here, in NumPy only:

- *Location*: each palm centre relative to the human's nearest body landmark, in the torso frame,
  divided by the body scale (shoulder width); the error is the distance between the human's and
  the robot's relative vectors (same landmark name on both). *Agreement*: among frames whose
  human palm is within `location_radius` scales of a landmark, the share where the robot palm's
  nearest landmark has the same name, up to ties of `location_tie` scales (see `location`).
- *Orientation*: palm normal and pointing direction (wrist → middle fingertip, or → palm centre
  on a hand without fingers) angles, in the torso frame.
- *Handshape*: per robot finger, flexion = 1 − |tip − palm| / (the same at rest), clipped to
  [0, 1]. Five fingers map to the three of a Dex3 hand as the finger retargeting maps them: thumb →
  thumb, index → index, and middle, ring and pinky (mean) → middle. Thumb opposition: the thumb
  tip's height over the palm along the palm normal, per hand length.
- *Movement*: DTW distance of the palm paths (relative to the sternum, torso frame, per scale),
  path-length ratio robot/human and the correlation of the speed profiles.
- *Contact*: per frame and channel (hand-hand, each hand to face, to chest), the human is in
  contact when its surfaces come within `contact_eps`; the robot when its geoms do without
  penetrating deeper than `penetration_tol`, within `robot_eps` (MuJoCo's distances between
  the exact hulls, `embodiments.robot_contacts`), by default the human's ε at hand scale
  (`robot_contact_eps`: a Dex3 hand is 1.42 human hands long; the IK's proxy margin leaves robot
  touches at 1.3-1.7 cm, and keeps non-touching gaps at hand scale).
  Precision, recall and F1 over frames, and over events (runs of contact frames in a channel,
  matched when a human and a robot run overlap: `contact_events`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from embody.metrics.trajectory import dtw_distance

SIDES = ("left", "right")
#: Landmarks a hand's location is measured against (face and trunk).
LOCATION_LANDMARKS = ("head_top", "forehead", "left_eye", "right_eye", "nose", "mouth", "chin",
                      "left_cheek", "right_cheek", "throat", "left_shoulder", "right_shoulder",
                      "sternum", "belly", "left_hip", "right_hip")
#: Contact channels, in this order in `Track.contact`.
CONTACTS = ("hands", "left_face", "right_face", "left_chest", "right_chest")
#: Robot finger ← human fingers (mean): the mapping `embody.retarget.hands` uses.
FINGER_SOURCES = {"thumb": ("thumb",), "index": ("index",), "middle": ("middle", "ring", "pinky")}


@dataclass
class Track:
    """One embodiment over a sequence, in a frame with x forward, y left, z up.

    `points` (T,K,3) are landmarks named `names`; `normals` (T,2,3) palm normals [left, right];
    `torso` (T,3,3) the torso's orientation (columns: its forward, left, up axes); `scale` the
    body scale (m); `rest` landmark positions at rest (K,3) for handshape normalisation;
    `contact` (T,len(CONTACTS)) closest surface distances (m), NaN where not measured.
    """

    names: tuple[str, ...]
    points: np.ndarray
    normals: np.ndarray
    torso: np.ndarray
    scale: float
    rest: np.ndarray
    contact: np.ndarray | None = None
    fps: float = 30.0
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def has(self, name: str) -> bool:
        return name in self.names

    def point(self, name: str) -> np.ndarray:
        return self.points[:, self.names.index(name)]

    def local(self, v: np.ndarray) -> np.ndarray:
        """Vectors (T,...,3) expressed in the torso frame."""
        return np.einsum("tba,t...b->t...a", self.torso, v)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def _landmarks(human: Track, robot: Track) -> list[str]:
    return [n for n in LOCATION_LANDMARKS if human.has(n) and robot.has(n)]


def relative_location(track: Track, side: str, names: list[str], nearest: np.ndarray) -> np.ndarray:
    """Palm − landmark `names[nearest[t]]` in the torso frame, per scale (T,3)."""
    palm = track.point(f"{side}_palm")
    lms = np.stack([track.point(n) for n in names], 1)
    rel = palm - lms[np.arange(len(palm)), nearest]
    return track.local(rel) / track.scale


def nearest_landmark(track: Track, side: str, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Index into `names` of the palm's nearest landmark (T,) and its distance per scale (T,)."""
    d = _distances(track, side, names)
    k = d.argmin(1)
    return k, d[np.arange(len(d)), k]


def _distances(track: Track, side: str, names: list[str]) -> np.ndarray:
    """Palm to each landmark in `names`, per scale (T,L)."""
    lms = np.stack([track.point(n) for n in names], 1)
    return np.linalg.norm(lms - track.point(f"{side}_palm")[:, None], axis=-1) / track.scale


def location(human: Track, robot: Track, radius: float, tie: float = 0.0) -> dict[str, np.ndarray]:
    """Per frame and hand (T,2): location error (scales), nearest landmark (human), its
    distance, whether the human hand is near it, and whether the robot's nearest agrees.

    Agreement allows ties of `tie` body scales: the robot's nearest landmark agrees when it is
    the human's, or when either body's palm is within `tie` as near to the other's choice as to
    its own (face landmarks lie 1.5-4 cm apart, and a palm a hand's width from the face is at
    mouth and chin alike: which one is "nearest" is then decided by millimetres, not by the sign).
    `exact` is the agreement without ties."""
    names = _landmarks(human, robot)
    err, near, agree, exact, idx, dist = [], [], [], [], [], []
    rows = np.arange(len(human.points))
    for side in SIDES:
        dh, dr = _distances(human, side, names), _distances(robot, side, names)
        k, kr = dh.argmin(1), dr.argmin(1)
        d = dh[rows, k]
        vh = relative_location(human, side, names, k)
        vr = relative_location(robot, side, names, k)
        err.append(np.linalg.norm(vh - vr, axis=-1))
        near.append(d < radius)
        exact.append(kr == k)
        agree.append((kr == k) | (dh[rows, kr] - d <= tie) | (dr[rows, k] - dr[rows, kr] <= tie))
        idx.append(k)
        dist.append(d)
    return {"err": np.stack(err, 1), "near": np.stack(near, 1), "agree": np.stack(agree, 1),
            "exact": np.stack(exact, 1), "landmark": np.stack(idx, 1), "distance": np.stack(dist, 1),
            "names": np.array(names)}


def orientation(human: Track, robot: Track) -> dict[str, np.ndarray]:
    """Palm-normal and pointing-direction angle errors (T,2), degrees, in each torso frame."""
    palm = _angle_deg(human.local(human.normals), robot.local(robot.normals))
    point = []
    for side in SIDES:
        tip = f"{side}_middle_tip" if human.has(f"{side}_middle_tip") and robot.has(f"{side}_middle_tip") \
            else f"{side}_palm"
        dirs = [t.local(t.point(tip) - t.point(f"{side}_wrist")) for t in (human, robot)]
        point.append(_angle_deg(*dirs))
    return {"palm_deg": palm, "pointing_deg": np.stack(point, 1)}


def flexion(track: Track, side: str, finger: str) -> np.ndarray:
    """1 − |tip − palm| / (the same at rest), clipped to [0, 1] (T,)."""
    tip, palm = f"{side}_{finger}_tip", f"{side}_palm"
    d = np.linalg.norm(track.point(tip) - track.point(palm), axis=-1)
    i, j = track.names.index(tip), track.names.index(palm)
    return np.clip(1.0 - d / np.linalg.norm(track.rest[i] - track.rest[j]), 0.0, 1.0)


def opposition(track: Track, side: str) -> np.ndarray:
    """Thumb tip height over the palm along the palm normal, per hand length (T,)."""
    s = 0 if side == "left" else 1
    v = track.point(f"{side}_thumb_tip") - track.point(f"{side}_palm")
    far = f"{side}_middle_tip" if track.has(f"{side}_middle_tip") else f"{side}_index_tip"
    length = np.linalg.norm(track.rest[track.names.index(far)] - track.rest[track.names.index(f"{side}_wrist")])
    return (v * track.normals[:, s]).sum(-1) / length


def handshape(human: Track, robot: Track) -> dict[str, np.ndarray]:
    """Per robot finger flexion |human − robot| (T,2,F) and thumb opposition error (T,2)."""
    flex, opp, fingers = [], [], []
    for side in SIDES:
        row = []
        for finger, sources in FINGER_SOURCES.items():
            if not robot.has(f"{side}_{finger}_tip"):
                continue
            hum = np.mean([flexion(human, side, f) for f in sources], axis=0)
            row.append(np.abs(hum - flexion(robot, side, finger)))
            fingers.append(finger) if side == "left" else None
        flex.append(np.stack(row, -1) if row else np.zeros((len(human.points), 0)))
        opp.append(np.abs(opposition(human, side) - opposition(robot, side))
                   if robot.has(f"{side}_thumb_tip") else np.full(len(human.points), np.nan))
    return {"flexion_err": np.stack(flex, 1), "opposition_err": np.stack(opp, 1),
            "fingers": np.array(fingers)}


def palm_paths(track: Track) -> np.ndarray:
    """Palms relative to the sternum, torso frame, per scale (T,2,3)."""
    palms = np.stack([track.point(f"{s}_palm") for s in SIDES], 1)
    return track.local(palms - track.point("sternum")[:, None]) / track.scale


def movement(human: Track, robot: Track) -> dict[str, float]:
    """DTW of the palm paths (scales), path-length ratio robot/human, speed-profile correlation."""
    ph, pr = palm_paths(human), palm_paths(robot)
    dtw = float(np.mean([dtw_distance(ph[:, s], pr[:, s]) for s in range(2)]))
    vh = np.linalg.norm(np.diff(ph, axis=0), axis=-1)
    vr = np.linalg.norm(np.diff(pr, axis=0), axis=-1)
    ratio = float(vr.sum() / vh.sum()) if vh.sum() > 1e-9 else float("nan")
    corr = []
    for s in range(2):
        if len(vh) > 2 and vh[:, s].std() > 1e-9 and vr[:, s].std() > 1e-9:
            corr.append(float(np.corrcoef(vh[:, s], vr[:, s])[0, 1]))
    return {"movement_dtw": dtw, "path_ratio": ratio,
            "speed_corr": float(np.mean(corr)) if corr else float("nan")}


def hand_length(points: np.ndarray, names) -> float | None:
    """Mean wrist → middle fingertip distance of both hands at rest (points (K,3) named `names`),
    None on a hand without a middle finger."""
    names = list(names)
    out = []
    for s in SIDES:
        if f"{s}_wrist" not in names or f"{s}_middle_tip" not in names:
            return None
        out.append(np.linalg.norm(points[names.index(f"{s}_middle_tip")] - points[names.index(f"{s}_wrist")]))
    return float(np.mean(out))


def hand_ratio(human_rest: np.ndarray, human_names, robot_rest: np.ndarray, robot_names,
               fallback: float) -> float:
    """Robot hand length over the human's (`fallback`, e.g. the body-scale ratio, without fingers)."""
    h, r = hand_length(human_rest, human_names), hand_length(robot_rest, robot_names)
    return r / h if h and r else fallback


def robot_contact_eps(human: Track, robot: Track, eps: float) -> float:
    """The robot's contact ε: the human's at hand scale (ε × robot/human hand length; G1 Dex3:
    1.42 → 2.1 cm). A contact is a gap small against the hands that make it, as locations are
    offsets per body scale; the IK keeps non-touching gaps at the same hand scale
    (`embody.retarget.hand_clearance`), so both sides of the threshold are mapped alike."""
    return eps * hand_ratio(human.rest, human.names, robot.rest, robot.names, robot.scale / human.scale)


def contacts(human: Track, robot: Track, eps: float, penetration: float,
             robot_eps: float | None = None) -> dict[str, np.ndarray]:
    """Frame events (T,C) of human and robot contact, robot penetrations, and P/R/F1 counts."""
    hc = human.contact if human.contact is not None else np.full((len(human.points), len(CONTACTS)), np.nan)
    rc = robot.contact if robot.contact is not None else np.full_like(hc, np.nan)
    measured = np.isfinite(hc) & np.isfinite(rc)
    h = measured & (hc < eps)
    pen = measured & (rc < -penetration)
    r = measured & (rc < (robot_contact_eps(human, robot, eps) if robot_eps is None else robot_eps)) & ~pen
    return {"human": h, "robot": r, "penetration": pen, "tp": h & r}


def _runs(x: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous True runs [start, end) of a (T,) mask."""
    d = np.diff(np.concatenate([[0], x.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def contact_events(human: np.ndarray, robot: np.ndarray) -> dict[str, int]:
    """Event counts of (T,C) contact masks: an event is a run of contact frames in one channel; a
    human event is found when a robot event of the same channel overlaps it, and a robot event
    is right when it overlaps a human one (a touch a few frames early or late is the same touch;
    the frame counts of `contacts` score its timing)."""
    out = {"human": 0, "robot": 0, "found": 0, "right": 0}
    for c in range(human.shape[1]):
        hr, rr = _runs(human[:, c]), _runs(robot[:, c])
        out["human"] += len(hr)
        out["robot"] += len(rr)
        out["found"] += sum(any(a < d and c0 < b for c0, d in rr) for a, b in hr)
        out["right"] += sum(any(a < d and c0 < b for c0, d in hr) for a, b in rr)
    return out


def event_f1(ev: dict[str, int]) -> tuple[float, float, float]:
    """Precision, recall and F1 of `contact_events` counts."""
    p = ev["right"] / ev["robot"] if ev["robot"] else float("nan")
    r = ev["found"] / ev["human"] if ev["human"] else float("nan")
    f = 2 * p * r / (p + r) if ev["robot"] and ev["human"] and (p + r) > 0 else (
        0.0 if (ev["robot"] or ev["human"]) else float("nan"))
    return p, r, f


def _f1(tp: int, hp: int, rp: int) -> tuple[float, float, float]:
    p = tp / rp if rp else float("nan")
    r = tp / hp if hp else float("nan")
    f = 2 * p * r / (p + r) if rp and hp and (p + r) > 0 else (0.0 if (rp or hp) else float("nan"))
    return p, r, f


def compare(human: Track, robot: Track, *, radius: float = 0.5, eps: float = 0.015,
            penetration: float = 0.002, robot_eps: float | None = None, tie: float = 0.0
            ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """All fidelity measures: per-frame arrays and the sequence's aggregates (flat floats)."""
    if len(human.points) != len(robot.points):
        raise ValueError(f"frame counts differ: human {len(human.points)}, robot {len(robot.points)}")
    loc = location(human, robot, radius, tie)
    ori = orientation(human, robot)
    shape = handshape(human, robot)
    mov = movement(human, robot)
    con = contacts(human, robot, eps, penetration, robot_eps)
    near = loc["near"]
    tp, hp, rp = int(con["tp"].sum()), int(con["human"].sum()), int(con["robot"].sum())
    p, r, f = _f1(tp, hp, rp)
    ev = contact_events(con["human"], con["robot"])
    ep, er, ef = event_f1(ev)
    flex = shape["flexion_err"]
    metrics = {
        "location_err": float(loc["err"].mean()),
        "location_err_mm": float(loc["err"].mean() * robot.scale * 1000.0),
        "location_err_near": float(loc["err"][near].mean()) if near.any() else float("nan"),
        "location_agree_pct": float(100.0 * loc["agree"][near].mean()) if near.any() else float("nan"),
        "location_agree_exact_pct": float(100.0 * loc["exact"][near].mean()) if near.any() else float("nan"),
        "location_near_frames": float(near.sum()),
        "palm_deg": float(ori["palm_deg"].mean()),
        "pointing_deg": float(ori["pointing_deg"].mean()),
        "handshape_err": float(flex.mean()) if flex.size else float("nan"),
        "thumb_opposition_err": float(np.nanmean(shape["opposition_err"]))
        if np.isfinite(shape["opposition_err"]).any() else float("nan"),
        **mov,
        "contact_precision": p, "contact_recall": r, "contact_f1": f,
        "contact_frames_human": float(hp), "contact_frames_robot": float(rp), "contact_tp": float(tp),
        "contact_event_precision": ep, "contact_event_recall": er, "contact_event_f1": ef,
        **{f"contact_events_{k}": float(v) for k, v in ev.items()},
        "penetration_frames": float(con["penetration"].any(1).sum()),
        "contact_eps_robot": float(robot_contact_eps(human, robot, eps) if robot_eps is None else robot_eps),
    }
    frames = {"location_err": loc["err"], "location_landmark": loc["landmark"],
              "location_distance": loc["distance"], "location_agree": loc["agree"],
              "palm_deg": ori["palm_deg"], "pointing_deg": ori["pointing_deg"],
              "contact_human": con["human"], "contact_robot": con["robot"]}
    return frames, metrics


def compare_with(human: Track, robot: Track, cfg) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """`compare` with the thresholds of a `FidelityConfig`."""
    return compare(human, robot, radius=cfg.location_radius, eps=cfg.contact_eps,
                   penetration=cfg.penetration_tol, robot_eps=cfg.robot_contact_eps, tie=cfg.location_tie)


def resample_track(track: Track, rate: float, times: np.ndarray | None = None) -> Track:
    """`track` at `rate` Hz on the exported control-rate grid (`embody.retarget.limits.resample`:
    t = k / rate over the same duration), or at `times` (s, the source times of a retimed
    array's samples: `retarget.dynamics_limits.Retimed.source_time`): the human side of a
    comparison with the exported array.
    Landmarks, palm normals (renormalised), contact distances and per-frame extras are linearly
    interpolated; torso rotations too, then projected back onto SO(3) (SVD): frames are close."""
    t_src = np.arange(len(track.points)) / track.fps
    if times is None:
        t_dst = np.arange(int(np.floor(t_src[-1] * rate + 1e-9)) + 1) / rate
    else:
        t_dst = np.clip(np.asarray(times, dtype=np.float64), 0.0, t_src[-1])
    n = len(t_dst)

    def lerp(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        flat = a.reshape(len(a), -1)
        return np.stack([np.interp(t_dst, t_src, flat[:, j]) for j in range(flat.shape[1])], 1
                        ).reshape((n,) + a.shape[1:])

    normals = lerp(track.normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    u, _, vt = np.linalg.svd(lerp(track.torso))
    torso = u @ vt
    torso = np.where((np.linalg.det(torso) < 0)[:, None, None], u @ np.diag([1.0, 1.0, -1.0]) @ vt, torso)
    extra = {k: lerp(v) for k, v in track.extra.items() if np.ndim(v) and len(v) == len(track.points)}
    return Track(names=track.names, points=lerp(track.points), normals=normals, torso=torso,
                 scale=track.scale, rest=track.rest,
                 contact=None if track.contact is None else lerp(track.contact), fps=float(rate), extra=extra)
