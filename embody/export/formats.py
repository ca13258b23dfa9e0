"""Writers and readers of the exported trajectory formats, one per consumer.

* `npz`: embody's own (q float64, joint names, dt, source id, robot, text, validation JSON,
  `source_time` (T,): each sample's time (s) on the source motion's timeline, which differs from
  k·dt where the torque and ZMP limits slowed the motion down, `retarget.dynamics_limits`), plus
  the low-level command fields when written for a robot (`embody.export.control`): `qd`, `tau_ff`
  (T,n) and `kp`, `kd` (n,) per joint, `control_rate_hz`: what a Unitree `LowCmd` takes per motor.
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
the root columns repeat MuJoCo's `qpos0` root. `read_trajectory` returns the joint array exactly
as its consumer would see it (float32 where the consumer casts), with the rate the file states,
which is what the export and `export --check` validate. It treats the file as hostile: size and
frame count are bounded before anything is parsed, and non-finite values, a missing or absurd
rate, or a layout that differs from the robot's are refused (`InputError`).
"""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import stat
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Callable, Literal, Sequence

import mujoco
import numpy as np
import pandas as pd

from embody.errors import InputError
from embody.io import safe_pickle
from embody.io.safe_pickle import Budget

ExportFormat = Literal["npz", "csv", "gmr", "beyondmimic"]

#: Bytes one value may take as text (`%.17g`: sign, 17 digits, point, exponent, delimiter):
#: with the frame bound it bounds a trajectory file's size before it is parsed.
TEXT_BYTES_PER_VALUE = 32
#: Columns a file may carry besides the joints (time or root pose) and its fixed overhead
#: (npz members' headers and metadata, the pickle's keys).
EXTRA_COLUMNS = 8
FILE_OVERHEAD_BYTES = 1 << 20
#: Largest tolerated |‖quaternion‖ − 1| of a root rotation (float32 text rounds to ~1e-7).
QUAT_NORM_TOLERANCE = 1e-3
#: Longest joint name an npz may carry (characters): bounds the `joint_names` member.
MAX_NAME_CHARS = 256


@dataclass(frozen=True)
class Layout:
    """What an exported file carries besides the joints (root pose, names, timing)."""

    joint_names: tuple[str, ...]
    dt: float
    root_pos: np.ndarray  # (3,) world position of the floating root
    root_quat_wxyz: np.ndarray  # (4,) MuJoCo order
    meta: dict[str, Any]
    #: Low-level command arrays (`embody.export.control.CONTROL_FIELDS`); npz only.
    control: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class FileTrajectory:
    """An exported file as its consumer reads it."""

    q: np.ndarray  # (T, n) float64, after the consumer's own cast
    rate_hz: float | None  # the rate the file states; None where the format has none (BeyondMimic)


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


def _npz_data(q: np.ndarray, lay: Layout) -> bytes:
    arrays = {"q": q, "dt": np.float64(lay.dt), "joint_names": np.array(lay.joint_names),
              "source_id": np.array(lay.meta.get("id", "")), "robot": np.array(lay.meta.get("robot", "")),
              "text": np.array(lay.meta.get("text", "")),
              "validation": np.array(json.dumps(lay.meta.get("validation", {}), sort_keys=True,
                                                default=float)),
              **{k: np.asarray(v, dtype=np.float64) for k, v in lay.control.items()}}
    if lay.meta.get("source_time") is not None:
        arrays["source_time"] = np.asarray(lay.meta["source_time"], dtype=np.float64)
    return _npz_bytes(arrays)


def _csv_data(q: np.ndarray, lay: Layout) -> bytes:
    frame = pd.DataFrame(q, columns=list(lay.joint_names))
    frame.insert(0, "time", np.arange(len(q)) * lay.dt)
    return frame.to_csv(index=False, lineterminator="\n", float_format="%.17g").encode("utf-8")


def _gmr_data(q: np.ndarray, lay: Layout) -> bytes:
    t = len(q)
    motion = {"fps": _fps(lay.dt),
              "root_pos": np.tile(lay.root_pos, (t, 1)),
              "root_rot": np.tile(lay.root_quat_wxyz[[1, 2, 3, 0]], (t, 1)),  # wxyz -> xyzw
              "dof_pos": np.asarray(q, dtype=np.float64),
              "local_body_pos": None,
              "link_body_list": None}
    return pickle.dumps(motion, protocol=4)


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


def beyondmimic_columns(joint_names: Sequence[str]) -> tuple[list[int], list[int]]:
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


def companion_files(path: Path, fmt: ExportFormat) -> list[Path]:
    """Files an exported `path` comes with (BeyondMimic's side file), to remove or copy with it."""
    return [beyondmimic_extra_path(path)] if fmt == "beyondmimic" else []


def _beyondmimic_data(q: np.ndarray, lay: Layout) -> bytes:
    t = len(q)
    main, _ = beyondmimic_columns(lay.joint_names)
    motion = np.hstack([np.tile(lay.root_pos, (t, 1)),
                        np.tile(lay.root_quat_wxyz[[1, 2, 3, 0]], (t, 1)), q[:, main]])
    buf = io.BytesIO()
    np.savetxt(buf, motion, delimiter=",", fmt="%.17g")
    return buf.getvalue()


def _beyondmimic_extra_data(q: np.ndarray, lay: Layout) -> bytes | None:
    """The side file's contents, or None when the csv carries every joint."""
    _, extra = beyondmimic_columns(lay.joint_names)
    if not extra:
        return None
    buf = io.BytesIO()
    np.savetxt(buf, q[:, extra], delimiter=",", fmt="%.17g", comments="",
               header=",".join(lay.joint_names[i] for i in extra))
    return buf.getvalue()


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


def max_file_bytes(n_joints: int, max_frames: int) -> int:
    """Largest trajectory file read for a robot of `n_joints` (any format): `max_frames` rows
    of joints plus time/root columns as text, and a fixed overhead."""
    return max_frames * (n_joints + EXTRA_COLUMNS) * TEXT_BYTES_PER_VALUE + FILE_OVERHEAD_BYTES


def open_regular(path: Path, max_bytes: int) -> BinaryIO:
    """`path` opened for reading if it is a regular file (not a symlink, FIFO or device) of at
    most `max_bytes`; anything else is an InputError, raised before a byte is read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise InputError(path, None, "missing") from None
    except OSError as exc:
        reason = "a symbolic link (refused)" if path.is_symlink() else exc.strerror or str(exc)
        raise InputError(path, None, f"cannot open: {reason}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputError(path, None, "not a regular file")
        if info.st_size > max_bytes:
            raise InputError(path, None, f"{info.st_size} bytes is more than the {max_bytes} a "
                                         "trajectory of io.max_frames frames can take")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _number_array(value: Any, path: Path, key: str, shape: Sequence[int | None]) -> np.ndarray:
    """`value` as finite float64 of `shape` (None: any length); other dtypes (bool, complex,
    text, objects), other shapes and NaN/inf are refused."""
    try:
        arr = np.asarray(value)
    except Exception:  # an object whose conversion fails is not a number
        raise InputError(path, key, f"not numeric (type {type(value).__name__})") from None
    if arr.dtype.kind not in "fiu":
        raise InputError(path, key, f"expected real numbers, got {arr.dtype} values")
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        want = "(" + ", ".join("T" if s is None else str(s) for s in shape) + ")"
        raise InputError(path, key, f"expected shape {want}, got {arr.shape}")
    out = arr.astype(np.float64)
    if not np.isfinite(out).all():
        raise InputError(path, key, "contains non-finite values (NaN or inf)")
    return out


def _rate(value: Any, path: Path, key: str) -> float:
    """A stated frame rate (Hz) or step (s) as a positive finite float (bool refused)."""
    if isinstance(value, (bool, np.bool_)):
        raise InputError(path, key, "expected a number, got a bool")
    arr = _number_array(value, path, key, ()) if np.ndim(value) == 0 else None
    if arr is None:
        raise InputError(path, key, f"expected one number, got shape {np.shape(value)}")
    number = float(arr)
    if not number > 0:
        raise InputError(path, key, f"must be > 0, got {number:g}")
    return number


def _frames(path: Path, frames: int, max_frames: int) -> None:
    if frames < 1:
        raise InputError(path, "q", "no frames")
    if frames > max_frames:
        raise InputError(path, "q", f"{frames} frames exceeds io.max_frames={max_frames}")


def _scan_lines(fh: BinaryIO, path: Path, names: tuple[str, ...], max_lines: int) -> None:
    """Stream a text file once before it is parsed, refusing it past `max_lines` lines or at a
    line longer than a row (or the header) of this robot can be: a parser then holds at most
    that many short rows."""
    longest = max((len(names) + EXTRA_COLUMNS) * TEXT_BYTES_PER_VALUE,
                  len(",".join(["time", *names]).encode("utf-8")) + 64)
    for i, line in enumerate(iter(lambda: fh.readline(longest + 2), b"")):
        if i >= max_lines:
            raise InputError(path, "q", f"more than {max_lines} lines (io.max_frames)")
        if len(line) > longest:
            raise InputError(path, f"line {i + 1}", f"longer than {longest} bytes")
    fh.seek(0)


def _root(root_pos: np.ndarray, root_xyzw: np.ndarray, path: Path, keys: tuple[str, str]) -> None:
    """The root pose must be finite (checked by the caller) and a unit quaternion."""
    norm = np.linalg.norm(root_xyzw, axis=1)
    if norm.size and np.abs(norm - 1.0).max() > QUAT_NORM_TOLERANCE:
        raise InputError(path, keys[1], f"not a unit quaternion (norm {norm.min():.4g}.."
                                        f"{norm.max():.4g})")


def _read_npz(fh: BinaryIO, path: Path, names: tuple[str, ...], max_frames: int) -> FileTrajectory:
    from embody.io.fields import npz_shapes

    shapes = npz_shapes(fh)  # type: ignore[arg-type]  # headers only, before anything is inflated
    for key in ("q", "dt"):
        if key not in shapes:
            raise InputError(path, key, "missing")
    shape, dtype = shapes["q"]
    if len(shape) != 2 or shape[1] != len(names) or dtype.kind not in "fiu":
        raise InputError(path, "q", f"expected (T, {len(names)}) real numbers, got {shape} {dtype}")
    _frames(path, shape[0], max_frames)
    if math.prod(shapes["dt"][0]) != 1 or shapes["dt"][1].kind not in "fiu":
        raise InputError(path, "dt", f"expected one number, got {shapes['dt'][0]} {shapes['dt'][1]}")
    if "joint_names" in shapes:
        shape, dtype = shapes["joint_names"]
        if shape != (len(names),) or dtype.kind != "U" or dtype.itemsize > 4 * MAX_NAME_CHARS:
            raise InputError(path, "joint_names", f"expected {len(names)} names, got {shape} {dtype}")
    fh.seek(0)
    with np.load(fh, allow_pickle=False) as z:
        q = _number_array(z["q"], path, "q", (None, len(names)))
        rate = 1.0 / _rate(np.asarray(z["dt"]).reshape(()), path, "dt")
        if "joint_names" in shapes and tuple(str(n) for n in z["joint_names"]) != names:
            raise InputError(path, "joint_names", "differ from the robot's joints")
    return FileTrajectory(q, rate)


def _read_csv(fh: BinaryIO, path: Path, names: tuple[str, ...], max_frames: int) -> FileTrajectory:
    _scan_lines(fh, path, names, max_frames + 2)
    table = pd.read_csv(fh)
    if list(table.columns) != ["time", *names]:
        raise InputError(path, "columns", "expected time and the robot's joint names")
    for column in table.columns:
        if table[column].dtype.kind not in "fiu":
            raise InputError(path, str(column), f"not numeric ({table[column].dtype})")
    _frames(path, len(table), max_frames)
    time = _number_array(table["time"].to_numpy(), path, "time", (None,))
    q = _number_array(table[list(names)].to_numpy(), path, "q", (None, len(names)))
    rate = None
    if len(time) >= 2:
        step = np.diff(time)
        dt = (time[-1] - time[0]) / (len(time) - 1)
        if not dt > 0 or np.abs(step - dt).max() > 1e-6 * dt:
            raise InputError(path, "time", "not evenly spaced and increasing")
        rate = 1.0 / dt
    return FileTrajectory(q, rate)


def _read_gmr(path: Path, names: tuple[str, ...], max_frames: int) -> FileTrajectory:
    motion = read_gmr(path)
    q = _number_array(motion["dof_pos"], path, "dof_pos", (None, len(names)))
    _frames(path, len(q), max_frames)
    pos = _number_array(motion["root_pos"], path, "root_pos", (len(q), 3))
    rot = _number_array(motion["root_rot"], path, "root_rot", (len(q), 4))
    _root(pos, rot, path, ("root_pos", "root_rot"))
    return FileTrajectory(q, _rate(motion["fps"], path, "fps"))


def _read_beyondmimic(fh: BinaryIO, path: Path, names: tuple[str, ...],
                      max_frames: int, side: Path | None) -> FileTrajectory:
    main, extra = beyondmimic_columns(names)
    _scan_lines(fh, path, names, max_frames + 1)
    with warnings.catch_warnings():  # an empty file is refused below, not warned about
        warnings.simplefilter("ignore")
        motion = np.loadtxt(fh, delimiter=",", ndmin=2)
    if motion.ndim != 2 or motion.shape[1] != 7 + len(main):
        raise InputError(path, "columns", f"expected 7 root + {len(main)} joint columns, got "
                                          f"{motion.shape[1] if motion.ndim == 2 else motion.shape}")
    _frames(path, len(motion), max_frames)
    motion = _number_array(motion.astype(np.float32), path, "rows", (None, 7 + len(main)))
    _root(motion[:, :3], motion[:, 3:7], path, ("root_pos", "root_quat"))
    q = np.empty((len(motion), len(names)))
    q[:, main] = motion[:, 7:]  # csv_to_npz: torch.from_numpy(...).to(float32)
    if extra:
        side = side or beyondmimic_extra_path(path)
        want = [names[i] for i in extra]
        with open_regular(side, max_file_bytes(len(names), max_frames)) as sh:
            _scan_lines(sh, side, names, max_frames + 2)
            table = pd.read_csv(sh)
        if list(table.columns) != want or len(table) != len(motion):
            raise InputError(side, "columns", f"expected {len(motion)} rows of {len(want)} joints "
                                              "(the robot's joints the csv lacks)")
        q[:, extra] = _number_array(table.to_numpy(), side, "rows", (None, len(want))
                                    ).astype(np.float32)
    return FileTrajectory(q, None)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    text = "".join(c if c.isprintable() else "?" for c in text)
    return text[:200] + ("…" if len(text) > 200 else "")


def read_trajectory(path: str | Path, fmt: ExportFormat, joint_names: Sequence[str], *,
                    max_frames: int, side: Path | None = None) -> FileTrajectory:
    """An exported file as its consumer reads it, refused (`InputError`) unless it is a regular
    file within the size and frame bounds holding finite joints of the robot's layout and,
    where the format states one, a finite positive rate. `side`: a BeyondMimic csv's side file
    when it is not beside `path` under its own name (a temp file being checked)."""
    path = Path(path)
    names = tuple(joint_names)
    if fmt not in WRITERS:
        raise InputError(path, "format", f"unknown export format {fmt!r}")
    with open_regular(path, max_file_bytes(len(names), max_frames)) as fh:
        try:
            if fmt == "npz":
                return _read_npz(fh, path, names, max_frames)
            if fmt == "csv":
                return _read_csv(fh, path, names, max_frames)
            if fmt == "gmr":
                return _read_gmr(path, names, max_frames)
            return _read_beyondmimic(fh, path, names, max_frames, side)
        except InputError as exc:  # its message may quote the file (a pickle's class names)
            raise InputError(exc.path, exc.field, _one_line(exc.message)) from None
        except Exception as exc:  # parsers raise many types on corrupt input
            raise InputError(path, None, f"cannot read {fmt} file: {type(exc).__name__}: "
                                         f"{_one_line(exc)}") from None


WRITERS: dict[str, tuple[str, Callable[[np.ndarray, Layout], bytes]]] = {
    "npz": (".npz", _npz_data), "csv": (".csv", _csv_data),
    "gmr": (".pkl", _gmr_data), "beyondmimic": (".csv", _beyondmimic_data)}
FORMATS: tuple[str, ...] = tuple(WRITERS)
#: Who reads each format (for the library index and the README).
CONSUMERS = {"npz": "embody (play, export --check)", "csv": "spreadsheets, generic tools",
             "gmr": "GMR motion pickle (TWIST and GMR-based trainers)",
             "beyondmimic": "BeyondMimic scripts/csv_to_npz.py (--input_fps = rate_hz); joints "
                            "it does not drive in <name>.extra_joints.csv"}


def trajectory_bytes(fmt: ExportFormat, q: np.ndarray, layout: Layout) -> tuple[str, bytes]:
    """(suffix, file contents) of q (T,n) in `fmt`."""
    if fmt not in WRITERS:
        raise InputError("<export>", "format", f"unknown export format {fmt!r}")
    suffix, writer = WRITERS[fmt]
    return suffix, writer(np.asarray(q, dtype=np.float64), layout)


def companion_bytes(fmt: ExportFormat, q: np.ndarray, layout: Layout,
                    path: Path) -> list[tuple[Path, bytes]]:
    """(path, contents) of the files that come with `path` in `fmt` (BeyondMimic's side file
    when the csv lacks some of the robot's joints)."""
    if fmt != "beyondmimic":
        return []
    side = _beyondmimic_extra_data(np.asarray(q, dtype=np.float64), layout)
    return [] if side is None else [(beyondmimic_extra_path(path), side)]


def write_trajectory(path_stem: Path, fmt: ExportFormat, q: np.ndarray, layout: Layout) -> Path:
    """Write q (T,n) in `fmt` next to `path_stem` (suffix added), atomically, with its companion
    files written first; returns the path."""
    from embody.export.atomic import write_atomic

    suffix, data = trajectory_bytes(fmt, q, layout)
    path = path_stem.with_name(path_stem.name + suffix)
    for side, side_data in companion_bytes(fmt, q, layout, path):
        write_atomic(side, side_data)
    write_atomic(path, data)
    return path
