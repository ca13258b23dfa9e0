"""Writers and readers of the exported trajectory formats, one per consumer.

* `npz`: embody's own (q float64, joint names, dt, source id, robot, text, validation JSON).
* `csv`: a `time` column then one column per joint (radians), exact float64 text (`%.17g`).
* `gmr`: GMR's motion pickle, as GMR's own writers build it (YanjieZe/GMR
  `scripts/smplx_to_robot.py`, `scripts/bvh_to_robot.py`: `root_pos = qpos[:, :3]`,
  `root_rot = qpos[:, 3:7][:, [1, 2, 3, 0]]` (MuJoCo's wxyz stored as **xyzw**),
  `dof_pos = qpos[:, 7:]` (every hinge in MJCF qpos order, fingers included),
  `local_body_pos = None`, `link_body_list = None`, `fps`), float64 as MuJoCo's qpos.
* `beyondmimic`: the csv BeyondMimic's `scripts/csv_to_npz.py` (HybridRobotics/whole_body_tracking)
  loads with `np.loadtxt(file, delimiter=",")` and casts to float32: no header, one row per frame,
  columns root position (3) | root quaternion **xyzw** (4; it reorders `[:, [3, 0, 1, 2]]` to wxyz)
  | joint positions. It assigns `motion[:, 7:]` to the 29 G1 joints it names, in its own order
  (`joint_pos[:, robot.find_joints(names, preserve_order=True)[0]] = motion_dof_pos`), so for a
  robot that has all of those joints the csv carries exactly them, in that order
  (`BEYONDMIMIC_G1_JOINTS`); the robot's other joints (the Dex3 fingers) go to a side file
  `<name>.extra_joints.csv`: a header row of joint names, then one row per frame (radians,
  `%.17g`), the csv's frames. A robot without BeyondMimic's G1 joints gets every joint in MJCF
  order and no side file. The frame rate is `--input_fps` (default 30), so the library records it.

Our robots' trajectories keep the floating root at its default pose (upper-body retargeting), so
the root columns repeat MuJoCo's `qpos0` root. Each reader returns the joint array exactly as its
consumer would see it (float32 where the consumer casts), which is what the export validates.
"""

from __future__ import annotations

import io
import json
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

import mujoco
import numpy as np
import pandas as pd

from embody.errors import InputError
from embody.io import safe_pickle
from embody.io.safe_pickle import Budget

ExportFormat = Literal["npz", "csv", "gmr", "beyondmimic"]


@dataclass(frozen=True)
class Layout:
    """What an exported file carries besides the joints (root pose, names, timing)."""

    joint_names: tuple[str, ...]
    dt: float
    root_pos: np.ndarray  # (3,) world position of the floating root
    root_quat_wxyz: np.ndarray  # (4,) MuJoCo order
    meta: dict[str, Any]


def root_pose(model: mujoco.MjModel, root_body: str) -> tuple[np.ndarray, np.ndarray]:
    """Default world pose (position, wxyz quaternion) of the root body at qpos0."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    b = model.body(root_body).id
    return data.xpos[b].copy(), data.xquat[b].copy()


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An `np.load`-able npz with fixed zip timestamps: equal trajectories, equal bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, value in arrays.items():
            arr = io.BytesIO()
            np.lib.format.write_array(arr, np.asarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, arr.getvalue())
    return buf.getvalue()


def _fps(dt: float) -> int | float:
    fps = 1.0 / dt
    return int(round(fps)) if abs(fps - round(fps)) < 1e-9 else fps


def _write_npz(path: Path, q: np.ndarray, lay: Layout) -> None:
    arrays = {"q": q, "dt": np.float64(lay.dt), "joint_names": np.array(lay.joint_names),
              "source_id": np.array(lay.meta.get("id", "")), "robot": np.array(lay.meta.get("robot", "")),
              "text": np.array(lay.meta.get("text", "")),
              "validation": np.array(json.dumps(lay.meta.get("validation", {}), sort_keys=True,
                                                default=float))}
    path.write_bytes(_npz_bytes(arrays))


def _write_csv(path: Path, q: np.ndarray, lay: Layout) -> None:
    frame = pd.DataFrame(q, columns=list(lay.joint_names))
    frame.insert(0, "time", np.arange(len(q)) * lay.dt)
    frame.to_csv(path, index=False, lineterminator="\n", float_format="%.17g")


def _write_gmr(path: Path, q: np.ndarray, lay: Layout) -> None:
    t = len(q)
    motion = {"fps": _fps(lay.dt),
              "root_pos": np.tile(lay.root_pos, (t, 1)),
              "root_rot": np.tile(lay.root_quat_wxyz[[1, 2, 3, 0]], (t, 1)),  # wxyz -> xyzw
              "dof_pos": np.asarray(q, dtype=np.float64),
              "local_body_pos": None,
              "link_body_list": None}
    path.write_bytes(pickle.dumps(motion, protocol=4))


#: The G1 joints BeyondMimic's `scripts/csv_to_npz.py` names (HybridRobotics/whole_body_tracking),
#: in its order: the csv's columns 7: are assigned to exactly these.
BEYONDMIMIC_G1_JOINTS = (
    "left_hip_pitch_joint", "left_hip_roll_joint", "left_hip_yaw_joint", "left_knee_joint",
    "left_ankle_pitch_joint", "left_ankle_roll_joint",
    "right_hip_pitch_joint", "right_hip_roll_joint", "right_hip_yaw_joint", "right_knee_joint",
    "right_ankle_pitch_joint", "right_ankle_roll_joint",
    "waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint",
    "left_shoulder_pitch_joint", "left_shoulder_roll_joint", "left_shoulder_yaw_joint",
    "left_elbow_joint", "left_wrist_roll_joint", "left_wrist_pitch_joint", "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint", "right_shoulder_roll_joint", "right_shoulder_yaw_joint",
    "right_elbow_joint", "right_wrist_roll_joint", "right_wrist_pitch_joint", "right_wrist_yaw_joint",
)
#: Suffix (replacing `.csv`) of the BeyondMimic side file with the joints BeyondMimic lacks.
BEYONDMIMIC_EXTRA_SUFFIX = ".extra_joints.csv"


def beyondmimic_columns(joint_names: tuple[str, ...] | list[str]) -> tuple[list[int], list[int]]:
    """Indices into `joint_names` of the csv's joint columns (in csv order) and of the side
    file's (MJCF order; empty when the csv carries every joint)."""
    names = list(joint_names)
    if set(BEYONDMIMIC_G1_JOINTS) <= set(names):
        main = [names.index(n) for n in BEYONDMIMIC_G1_JOINTS]
    else:
        main = list(range(len(names)))
    chosen = set(main)
    return main, [i for i in range(len(names)) if i not in chosen]


def beyondmimic_extra_path(path: Path) -> Path:
    """The side file next to a BeyondMimic csv `path`."""
    return path.with_name(path.name.removesuffix(".csv") + BEYONDMIMIC_EXTRA_SUFFIX)


def _write_beyondmimic(path: Path, q: np.ndarray, lay: Layout) -> None:
    t = len(q)
    main, extra = beyondmimic_columns(lay.joint_names)
    motion = np.hstack([np.tile(lay.root_pos, (t, 1)),
                        np.tile(lay.root_quat_wxyz[[1, 2, 3, 0]], (t, 1)), q[:, main]])
    np.savetxt(path, motion, delimiter=",", fmt="%.17g")
    side = beyondmimic_extra_path(path)
    if extra:
        np.savetxt(side, q[:, extra], delimiter=",", fmt="%.17g", comments="",
                   header=",".join(lay.joint_names[i] for i in extra))
    else:
        side.unlink(missing_ok=True)


def companion_files(path: Path, fmt: ExportFormat) -> list[Path]:
    """Files an exported `path` comes with (BeyondMimic's side file), to remove or copy with it."""
    return [beyondmimic_extra_path(path)] if fmt == "beyondmimic" else []


#: Largest GMR motion pickle read.
GMR_MAX_BYTES = 1 << 30
#: Floor of a GMR pickle's element budget (below it, small files are never refused by size).
GMR_MIN_ELEMENTS = 1 << 16


def read_gmr(path: Path) -> dict[str, Any]:
    """A GMR motion pickle as its consumers load it (`pickle.load`), read by `safe_pickle`:
    plain containers and numeric arrays only, no more values than the file has bytes."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(path, None, f"cannot read GMR motion pickle: {exc.strerror or exc}") from None
    budget = Budget(max_bytes=GMR_MAX_BYTES, max_elements=max(size, GMR_MIN_ELEMENTS))
    motion = safe_pickle.read(path, budget)
    if not isinstance(motion, dict):
        raise InputError(path, None, "a GMR motion pickle is a dict")
    for key in ("fps", "root_pos", "root_rot", "dof_pos"):
        if key not in motion:
            raise InputError(path, key, "missing")
    return motion


def _beyondmimic_joints(path: Path, csv_q: np.ndarray, joint_names: tuple[str, ...]) -> np.ndarray:
    """The robot's full joint array from a BeyondMimic csv's joint columns and its side file."""
    main, extra = beyondmimic_columns(joint_names)
    if csv_q.shape[1] != len(main):
        raise InputError(path, None, f"expected {len(main)} joint columns after the 7 root "
                         f"columns, got {csv_q.shape[1]}")
    q = np.empty((len(csv_q), len(joint_names)), dtype=np.float32)
    q[:, main] = csv_q
    if extra:
        side = beyondmimic_extra_path(path)
        try:
            table = pd.read_csv(side)
        except (OSError, ValueError) as exc:
            raise InputError(side, None, f"cannot read the side file: {exc}") from None
        want = [joint_names[i] for i in extra]
        if list(table.columns) != want or len(table) != len(csv_q):
            raise InputError(side, None, f"expected {len(csv_q)} rows of {want}")
        q[:, extra] = table.to_numpy(np.float64).astype(np.float32)
    return q


def read_joint_positions(path: str | Path, fmt: ExportFormat, n_joints: int,
                         joint_names: tuple[str, ...] | list[str] | None = None) -> np.ndarray:
    """The joint array (T, n_joints) of an exported file, as its consumer reads it (float64 out;
    BeyondMimic's float32 cast applied first). A BeyondMimic csv needs the robot's `joint_names`
    to put its columns and its side file's back in the robot's order."""
    path = Path(path)
    if fmt == "npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                q = np.asarray(z["q"])
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(path, "q", f"cannot read: {exc}") from None
    elif fmt == "csv":
        try:
            table = pd.read_csv(path)
        except (OSError, ValueError) as exc:
            raise InputError(path, None, f"cannot read csv: {exc}") from None
        q = table.drop(columns=["time"], errors="ignore").to_numpy()
    elif fmt == "gmr":
        q = np.asarray(read_gmr(path)["dof_pos"])
    elif fmt == "beyondmimic":
        try:
            motion = np.loadtxt(path, delimiter=",", ndmin=2)
        except (OSError, ValueError) as exc:
            raise InputError(path, None, f"cannot read csv: {exc}") from None
        q = motion.astype(np.float32)[:, 7:]  # csv_to_npz: torch.from_numpy(...).to(float32)
        if joint_names is not None:
            q = _beyondmimic_joints(path, q, tuple(joint_names))
    else:
        raise InputError(path, "format", f"unknown export format {fmt!r}")
    if q.ndim != 2 or q.shape[1] != n_joints:
        raise InputError(path, "q", f"expected (T, {n_joints}) joint positions, got {q.shape}")
    return q.astype(np.float64)


WRITERS: dict[str, tuple[str, Callable[[Path, np.ndarray, Layout], None]]] = {
    "npz": (".npz", _write_npz), "csv": (".csv", _write_csv),
    "gmr": (".pkl", _write_gmr), "beyondmimic": (".csv", _write_beyondmimic)}
FORMATS: tuple[str, ...] = tuple(WRITERS)
#: Who reads each format (for the library index and the README).
CONSUMERS = {"npz": "embody (play, export --check)", "csv": "spreadsheets, generic tools",
             "gmr": "GMR motion pickle (TWIST and GMR-based trainers)",
             "beyondmimic": "BeyondMimic scripts/csv_to_npz.py (--input_fps = rate_hz); joints "
                            "it does not drive in <name>.extra_joints.csv"}


def write_trajectory(path_stem: Path, fmt: ExportFormat, q: np.ndarray, layout: Layout) -> Path:
    """Write q (T,n) in `fmt` next to `path_stem` (suffix added); returns the path."""
    if fmt not in WRITERS:
        raise InputError(path_stem, "format", f"unknown export format {fmt!r}")
    suffix, writer = WRITERS[fmt]
    path = path_stem.with_name(path_stem.name + suffix)
    writer(path, np.asarray(q, dtype=np.float64), layout)
    return path
