"""Derive a robot's `landmarks:` (and `palm_normals:`) from its MuJoCo geometry, for its YAML.

The rules mirror the body's (`embody.body.landmarks.RULES`): in the torso frame at the T-pose
(x forward, y left, z up; arms out, palms down), each landmark is a surface vertex of named
geoms: the support point in a direction (face: from the head's centre; chin = lowest front
point), on the midline or within a height band, then stored as an offset in its body's frame.

    python scripts/robot_landmarks.py unitree_g1_dex3   # prints YAML to paste
"""

from __future__ import annotations

import sys

import mujoco
import numpy as np

from embody.body.landmarks import RULES
from embody.config.robot import RobotConfig
from embody.robot import load_robot

#: Per robot: geoms (by index) of the head, torso, shoulders, hips; per side the wrist body,
#: palm geoms and fingertips (name → (proximal geom, distal geom)); head/torso split height.
ROBOTS = {
    "unitree_g1_dex3": {
        # the head mesh includes its neck mount (narrowest near z 0.33, a wide base at 0.28):
        # the face is the head above the neck, the throat on the neck's front
        "face": [38], "face_above": 0.335, "face_from_human": True, "torso": [35], "neck_z": 0.32,
        "hull": {"face": 39, "torso": 36},  # the collision meshes of the head and the torso
        "shoulder": {"left": ["left_shoulder_pitch_link", "left_shoulder_roll_link"],
                     "right": ["right_shoulder_pitch_link", "right_shoulder_roll_link"]},
        "hip": {"left": ["pelvis", "left_hip_pitch_link", "left_hip_roll_link"],
                "right": ["pelvis", "right_hip_pitch_link", "right_hip_roll_link"]},
        "hip_body": {"left": "left_hip_pitch_link", "right": "right_hip_pitch_link"},
        "wrist": {"left": "left_wrist_yaw_link", "right": "right_wrist_yaw_link"},
        "palm": {"left": [54], "right": [84]},
        "tips": {"left": {"thumb": (58, 60), "index": (66, 68), "middle": (62, 64)},
                 "right": {"thumb": (88, 90), "index": (96, 98), "middle": (92, 94)}},
    },
    "unitree_h1": {
        "face": [31], "face_above": 0.56, "torso": [31], "torso_below": 0.5, "neck_z": 0.53,
        "shoulder": {"left": ["left_shoulder_pitch_link", "left_shoulder_roll_link"],
                     "right": ["right_shoulder_pitch_link", "right_shoulder_roll_link"]},
        "hip": {"left": ["pelvis", "left_hip_pitch_link", "left_hip_roll_link", "left_hip_yaw_link"],
                "right": ["pelvis", "right_hip_pitch_link", "right_hip_roll_link", "right_hip_yaw_link"]},
        "hip_body": {"left": "left_hip_pitch_link", "right": "right_hip_pitch_link"},
        "wrist": {"left": "left_elbow_link", "right": "right_elbow_link"},
        "wrist_point": {"left": [0.24, 0.0, -0.013], "right": [0.24, 0.0, -0.013]},
        "palm": {"left": [44], "right": [52]},
        "tips": {"left": {}, "right": {}},
    },
}
#: Body heights below the shoulder joint, in shoulder widths (measured on the mannequin).
STERNUM_DROP, BELLY_DROP = 0.54, 0.88
#: Face landmarks' heights as fractions from the head top (0) to the chin (1), on the mannequin.
FACE_HEIGHTS = {"forehead": 0.25, "left_eye": 0.44, "right_eye": 0.44, "nose": 0.71, "mouth": 0.92,
                "left_cheek": 0.75, "right_cheek": 0.75}


def surface(model: mujoco.MjModel, data: mujoco.MjData, geoms: list[int], torso: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Torso-frame surface points of `geoms` (mesh vertices; sampled spheres/capsules) and their geom."""
    pts, owner = [], []
    rng = np.random.default_rng(0)
    for g in geoms:
        t = model.geom_type[g]
        if t == mujoco.mjtGeom.mjGEOM_MESH:
            mid = model.geom_dataid[g]
            v = model.mesh_vert[model.mesh_vertadr[mid]: model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
            v = v.astype(np.float64)
        elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
            u = rng.normal(size=(4000, 3))
            v = u / np.linalg.norm(u, axis=1)[:, None] * model.geom_size[g][0]
        else:
            continue
        w = v @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        pts.append(w @ torso[:3, :3].T + torso[:3, 3])
        owner.append(np.full(len(v), g))
    return np.concatenate(pts), np.concatenate(owner)


#: Landmarks moved forward onto a collision hull (`hull`: geom per key) where a robot defines one.
HULL_FRONT = {**{n: "face" for n in ("forehead", "left_eye", "right_eye", "nose", "mouth", "chin", "left_cheek",
                                     "right_cheek")}, "sternum": "torso", "belly": "torso"}


def _hull_planes(m: mujoco.MjModel, d: mujoco.MjData, geom: int, torso: np.ndarray) -> np.ndarray:
    """Outward planes (n, c: n·p + c ≤ 0 inside) of a mesh geom's convex hull, torso frame."""
    from scipy.spatial import ConvexHull
    pts, _ = surface(m, d, [geom], torso)
    return ConvexHull(pts).equations


def _human_face() -> dict[str, np.ndarray]:
    """The rest body's face landmarks (torso frame: forward, left, up) and its body scale."""
    from embody.body import load_body_model
    from embody.body.landmarks import body_landmarks
    from embody.config import Config
    from embody.metrics.embodiments import BODY_TO_FLU
    import torch
    body = load_body_model(Config().body)
    lm = body_landmarks(body, np.zeros(10))
    with torch.no_grad():
        rest = body.joint_transforms(torch.zeros(1, 55, 3, dtype=torch.float64),
                                     torch.zeros(10, dtype=torch.float64)).numpy()
    pts, _ = lm.positions(rest)
    out = {n: pts[0, lm.index(n)] @ BODY_TO_FLU.T for n in ("head_top", "chin", *FACE_HEIGHTS)}
    out["scale"] = lm.scale
    return out


def _shoulder_width(m, d, spec, torso, geoms_of, bpose, support) -> float:
    """Distance between the two shoulder landmarks (the body scale), as found below."""
    tops = []
    for side in ("left", "right"):
        _, sj = bpose(spec["shoulder"][side][1])
        pts, _ = surface(m, d, geoms_of(spec["shoulder"][side]), torso)
        sel = np.abs(pts[:, 1] - sj[1]) < 0.02
        tops.append(pts[np.flatnonzero(sel)[support(pts[sel], (0, 0, 1))]])
    return float(np.linalg.norm(tops[0] - tops[1]))


def main(name: str) -> None:
    spec = ROBOTS[name]
    robot = load_robot(RobotConfig(name=name))
    m = robot.model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.qpos(robot.tpose)
    mujoco.mj_kinematics(m, d)
    torso = robot.torso_from_world

    def bpose(body: str) -> tuple[np.ndarray, np.ndarray]:
        b = m.body(body).id
        return torso[:3, :3] @ d.xmat[b].reshape(3, 3), torso[:3, :3] @ d.xpos[b] + torso[:3, 3]

    def geoms_of(bodies: list[str]) -> list[int]:
        ids = {m.body(b).id for b in bodies}
        return [g for g in range(m.ngeom) if m.geom_bodyid[g] in ids and m.geom_group[g] == 2]

    def support(p: np.ndarray, direction, centre=None) -> int:
        c = p.mean(0) if centre is None else centre
        dd = np.asarray(direction, dtype=np.float64)
        return int(np.argmax((p - c) @ (dd / np.linalg.norm(dd))))

    out: dict[str, tuple[str, np.ndarray]] = {}

    def put(lname: str, point: np.ndarray, geom: int, body: str | None = None) -> None:
        body = body or m.body(m.geom_bodyid[geom]).name
        r, o = bpose(body)
        out[lname] = (body, r.T @ (point - o))

    face, fo = surface(m, d, spec["face"], torso)
    keep = face[:, 2] > spec.get("face_above", -np.inf)
    face, fo = face[keep], fo[keep]
    top = face[support(face, (0, 0, 1))]
    chin = face[support(face, RULES["chin"].direction)]
    put("head_top", top, int(fo[support(face, (0, 0, 1))]))
    put("chin", chin, int(fo[support(face, RULES["chin"].direction)]))
    # the rest of the face: the human's layout (relative to the chin, per body scale; heights
    # per chin-to-top height) carried onto this head, then put on its front surface there,
    # so each landmark sits where the human's would (a support point per direction lands on
    # whatever this head's shape sticks out most: cheeks beside the nose, a nose in a visor slot)
    # (`face_from_human`; otherwise the front surface at the human's relative height per direction)
    human = _human_face()
    scale_r = _shoulder_width(m, d, spec, torso, geoms_of, bpose, support)
    k = np.array([scale_r / human["scale"]] * 2 + [(top[2] - chin[2]) / (human["head_top"][2] - human["chin"][2])])
    for lname, frac in FACE_HEIGHTS.items():
        if spec.get("face_from_human"):
            want = chin + k * (human[lname] - human["chin"])
            # the front surface at the wanted (left, up): heads differ most in depth
            lateral = np.linalg.norm(face[:, 1:] - want[1:], axis=1)
            i = int(np.argmax(face[:, 0] - 1e3 * np.maximum(lateral - lateral.min() - 0.004, 0.0)))
        else:
            z = top[2] - frac * (top[2] - chin[2])
            d2 = np.asarray(RULES[lname].direction, dtype=np.float64) * [1, 1, 0]
            score = (face - face.mean(0)) @ (d2 / np.linalg.norm(d2)) - 4.0 * np.abs(face[:, 2] - z)
            if RULES[lname].direction[1] == 0.0:  # a midline landmark stays on the midline (a visor
                score = np.where(np.abs(face[:, 1]) < 0.01, score, -np.inf)  # bump is not a forehead)
            i = int(np.argmax(score))
        put(lname, face[i], int(fo[i]))
    body_pts, bo = surface(m, d, spec["torso"] + spec["face"], torso)
    mid = np.abs(body_pts[:, 1]) < 0.02
    band = mid & (np.abs(body_pts[:, 2] - spec["neck_z"]) < 0.01)
    i = np.flatnonzero(band)[support(body_pts[band], (1, 0, 0))]
    put("throat", body_pts[i], int(bo[i]))
    for side in ("left", "right"):
        _, sj = bpose(spec["shoulder"][side][1])
        pts, po = surface(m, d, geoms_of(spec["shoulder"][side]), torso)
        sel = np.abs(pts[:, 1] - sj[1]) < 0.02
        i = np.flatnonzero(sel)[support(pts[sel], (0, 0, 1))]
        # carried by the torso, as the body's is by its collar (embody.body.landmarks.CARRIED_BY)
        put(f"{side}_shoulder", pts[i], int(po[i]), m.body(robot.spec.torso_body).name)
    scale = float(np.linalg.norm(
        (bpose(out["left_shoulder"][0])[0] @ out["left_shoulder"][1] + bpose(out["left_shoulder"][0])[1])
        - (bpose(out["right_shoulder"][0])[0] @ out["right_shoulder"][1] + bpose(out["right_shoulder"][0])[1])))
    z_sh = bpose(spec["shoulder"]["left"][1])[1][2]
    tpts, to = surface(m, d, spec["torso"], torso)
    tpts_keep = tpts[:, 2] < spec.get("torso_below", np.inf)
    for lname, drop in (("sternum", STERNUM_DROP), ("belly", BELLY_DROP)):
        z = max(z_sh - drop * scale, tpts[tpts_keep, 2].min() + 0.01)
        score = np.where(tpts_keep, tpts[:, 0] - 4.0 * np.abs(tpts[:, 2] - z) - 4.0 * np.abs(tpts[:, 1]),
                         -np.inf)
        i = int(np.argmax(score))
        put(lname, tpts[i], int(to[i]))
    for side, sign in (("left", 1.0), ("right", -1.0)):
        _, hz = bpose(spec["hip_body"][side])
        pts, po = surface(m, d, geoms_of(spec["hip"][side]), torso)
        sel = (np.abs(pts[:, 2] - hz[2]) < 0.03) & (sign * pts[:, 1] > 0)
        i = np.flatnonzero(sel)[support(pts[sel], (0, sign, 0))]
        put(f"{side}_hip", pts[i], int(po[i]))
        wr, wo = bpose(spec["wrist"][side])
        wpoint = wo + wr @ np.asarray(spec.get("wrist_point", {}).get(side, [0, 0, 0]))
        pts, po = surface(m, d, geoms_of([spec["wrist"][side]]), torso)
        i = int(np.argmin(np.linalg.norm(pts - wpoint, axis=1)))
        put(f"{side}_wrist", pts[i], int(po[i]))
        pts, po = surface(m, d, spec["palm"][side], torso)
        i = int(np.argmin(np.linalg.norm(pts - (pts.mean(0) + np.array([0, 0, -0.05])), axis=1)))
        put(f"{side}_palm", pts[i], int(po[i]))
        for finger, (g0, g1) in spec["tips"][side].items():
            pts, po = surface(m, d, [g1], torso)
            axis = d.geom_xpos[g1] - d.geom_xpos[g0]
            axis = torso[:3, :3] @ axis
            i = support(pts, axis)
            put(f"{side}_{finger}_tip", pts[i], int(po[i]))
    # onto the collision hull: MuJoCo collides (and the fidelity contacts measure) convex hulls,
    # so a landmark in a concavity of the visual mesh (G1: eyes 2 cm, nose 5.7 cm, sternum 1.2 cm
    # inside) is a place no hand can reach; moved forward to the hull's front it is where a
    # touch on it ends, as the human's landmarks are on the skin
    for lname, key in HULL_FRONT.items():
        if key not in spec.get("hull", {}) or lname not in out:
            continue
        eq = _hull_planes(m, d, spec["hull"][key], torso)
        body, off = out[lname]
        r, o = bpose(body)
        p = r @ off + o
        ahead = eq[:, 0] > 1e-6
        t = float(((-eq[ahead, 3] - eq[ahead, :3] @ p) / eq[ahead, 0]).min())
        out[lname] = (body, r.T @ (p + np.array([t, 0.0, 0.0]) - o))
    print("# Named landmarks (embody/body/landmarks.py names): body + offset in that body's frame,")
    print(f"# derived from the MuJoCo geometry by scripts/robot_landmarks.py {name}.")
    print("landmarks:")
    for lname, (body, off) in out.items():
        print(f"  {lname}: {{body: {body}, offset: [{off[0]:.4f}, {off[1]:.4f}, {off[2]:.4f}]}}")
    print("# Palm normal (palms down at the T-pose) in the wrist body's frame.")
    print("palm_normals:")
    for side in ("left", "right"):
        r, _ = bpose(spec["wrist"][side])
        n = r.T @ np.array([0.0, 0.0, -1.0])
        print(f"  {side}: {{body: {spec['wrist'][side]}, offset: [{n[0]:.4f}, {n[1]:.4f}, {n[2]:.4f}]}}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "unitree_g1_dex3")
