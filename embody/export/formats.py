"""Writers and readers of the exported trajectory formats, one per consumer.

* `npz`: embody's own (q float64, joint names, dt, source id, robot, text, validation JSON), plus
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
  | joint positions in MJCF order; the frame rate is its `--input_fps` argument (default 30), so
  the library records it. GMR's converter (`scripts/batch_gmr_pkl_to_csv.py`) writes the same
  columns from a motion pickle (`np.savetxt(..., delimiter=",")` of float32).

Our robots' trajectories keep the floating root at its default pose (upper-body retargeting), so
the root columns repeat MuJoCo's `qpos0` root. Each reader returns the joint array exactly as its
consumer would see it (float32 where the consumer casts), which is what the export validates.
"""

from __future__ import annotations

import io
import json
import pickle
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

import mujoco
import numpy as np
import pandas as pd

from embody.errors import InputError

ExportFormat = Literal["npz", "csv", "gmr", "beyondmimic"]


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
                                                default=float)),
              **{k: np.asarray(v, dtype=np.float64) for k, v in lay.control.items()}}
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


def _write_beyondmimic(path: Path, q: np.ndarray, lay: Layout) -> None:
    t = len(q)
    motion = np.hstack([np.tile(lay.root_pos, (t, 1)),
                        np.tile(lay.root_quat_wxyz[[1, 2, 3, 0]], (t, 1)), q])
    np.savetxt(path, motion, delimiter=",", fmt="%.17g")


class _ArraysOnly(pickle.Unpickler):
    """Unpickles plain containers and NumPy arrays only: a received library is data, not code."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
               ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a motion pickle")


def read_gmr(path: Path) -> dict[str, Any]:
    """A GMR motion pickle as its consumers load it (`pickle.load`), restricted to arrays."""
    try:
        with open(path, "rb") as f:
            motion = _ArraysOnly(f).load()
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ValueError) as exc:
        raise InputError(path, None, f"cannot read GMR motion pickle: {exc}") from None
    if not isinstance(motion, dict):
        raise InputError(path, None, "a GMR motion pickle is a dict")
    for key in ("fps", "root_pos", "root_rot", "dof_pos"):
        if key not in motion:
            raise InputError(path, key, "missing")
    return motion


def read_joint_positions(path: str | Path, fmt: ExportFormat, n_joints: int) -> np.ndarray:
    """The joint array (T, n_joints) of an exported file, as its consumer reads it (float64 out;
    BeyondMimic's float32 cast applied first)."""
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
             "beyondmimic": "BeyondMimic scripts/csv_to_npz.py (--input_fps = rate_hz)"}


def write_trajectory(path_stem: Path, fmt: ExportFormat, q: np.ndarray, layout: Layout) -> Path:
    """Write q (T,n) in `fmt` next to `path_stem` (suffix added); returns the path."""
    if fmt not in WRITERS:
        raise InputError(path_stem, "format", f"unknown export format {fmt!r}")
    suffix, writer = WRITERS[fmt]
    path = path_stem.with_name(path_stem.name + suffix)
    writer(path, np.asarray(q, dtype=np.float64), layout)
    return path
