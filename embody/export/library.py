"""The exported trajectory library: one file per validated sequence plus `library.csv` and
`library.json` indexes.

A trajectory is exported only if the file as written passes validation: it is read back the way
its consumer reads it (`embody.export.formats`, float32 cast included for BeyondMimic) and that
array is checked with MuJoCo and the robot's limits (`retarget.validation`): no joint-limit or
velocity-limit violations and no self-collision frames at any sample. The counters the run
stored must agree. The rest are listed in `excluded.csv` with the reason, so a user can see what
the library is missing and why. `check_library` re-validates a received library from its files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pandas as pd

from embody.csvsafe import csv_safe
from embody.errors import InputError
from embody.report.paths import safe_name
from embody.export.formats import (CONSUMERS, FORMATS, ExportFormat, Layout, read_joint_positions,
                                   root_pose, write_trajectory)
from embody.export.control import PHYSICS_CHECK_KEYS
from embody.retarget.validation import VALIDATION_KEYS

#: Validation counters that must be zero for a trajectory to be exported.
VIOLATION_KEYS = VALIDATION_KEYS
Format = ExportFormat
LIBRARY_VERSION = 2


@dataclass(frozen=True)
class Trajectory:
    """A robot joint trajectory at the control rate, with where it came from and how it scored."""

    id: str
    robot: str
    joint_names: tuple[str, ...]
    q: np.ndarray
    dt: float
    text: str = ""
    validation: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        q = np.asarray(self.q, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != len(self.joint_names):
            raise InputError(self.id, "q", f"expected (T, {len(self.joint_names)}), got {q.shape}")
        if not self.dt > 0:
            raise InputError(self.id, "dt", f"must be > 0, got {self.dt!r}")
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "joint_names", tuple(self.joint_names))

    @property
    def violations(self) -> dict[str, int]:
        """The non-zero validation counters among VIOLATION_KEYS (empty = valid): the rule
        `embody.verdicts.violations` that the run summary and the report count with too."""
        from embody.verdicts import violations
        return violations(self.validation)

    def layout(self, robot: Any | None = None) -> Layout:
        """What the writers need besides q (root pose from the robot's MJCF, when given)."""
        control: dict[str, np.ndarray] = {}
        if robot is not None:
            pos, quat = root_pose(robot.model, robot.spec.root_body)
            if robot.spec.actuation is not None:
                from embody.export.control import control_fields
                control = control_fields(robot, self.q, self.dt)
        else:
            pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
        return Layout(self.joint_names, self.dt, pos, quat,
                      {"id": self.id, "robot": self.robot, "text": self.text,
                       "validation": self.validation}, control)

    def save(self, path_stem: Path, fmt: ExportFormat = "npz", robot: Any | None = None) -> Path:
        """Write in `fmt` at `path_stem` + the format's suffix."""
        return write_trajectory(Path(path_stem), fmt, self.q, self.layout(robot))

    def save_npz(self, path: Path) -> Path:
        """An `np.load`-able npz with fixed zip timestamps: equal trajectories, equal bytes; with
        the command fields of the robot it names when that robot is known (as `export_library`)."""
        robot = None
        if self.robot:
            from embody.errors import ConfigError
            try:
                robot = _robot_named(self.robot)
            except ConfigError:
                robot = None
        return self.save(Path(path).with_suffix(""), "npz", robot)

    def save_csv(self, path: Path) -> Path:
        """Time column then one column per joint (radians), one row per control step."""
        return self.save(Path(path).with_suffix(""), "csv")

    @classmethod
    def load(cls, path: str | Path) -> "Trajectory":
        """Read an exported `.npz` (the CSV form lacks the metadata, so it is not accepted)."""
        path = Path(path)
        if path.suffix != ".npz":
            raise InputError(path, None, "expected an exported trajectory .npz")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise InputError(path, None, f"cannot read npz: {exc}") from None
        for key in ("q", "dt", "joint_names"):
            if key not in data:
                raise InputError(path, key, "missing")
        return cls(id=str(data.get("source_id", path.stem)), robot=str(data.get("robot", "")),
                   joint_names=tuple(str(n) for n in data["joint_names"]), q=data["q"],
                   dt=float(data["dt"]), text=str(data.get("text", "")),
                   validation=json.loads(str(data.get("validation", "{}"))))


def _remove_previous(out_dir: Path) -> None:
    """Delete the files a previous export listed, so a re-export never leaves stale ones."""
    index = out_dir / "library.csv"
    if index.is_file():
        for name in pd.read_csv(index, dtype=str, keep_default_na=False).get("file", []):
            if name and Path(name).name == name:
                (out_dir / name).unlink(missing_ok=True)


def _robot_named(name: str) -> Any:
    from embody.config.robot import RobotConfig
    from embody.robot import load_robot

    return load_robot(RobotConfig(name=name))


def file_validation(robot: Any, path: Path, fmt: ExportFormat, dt: float) -> dict[str, float]:
    """Validation counters of an exported file's joint array, read as its consumer reads it."""
    from embody.retarget.validation import validation_counts

    q = read_joint_positions(path, fmt, robot.n_joints)
    return validation_counts(robot, q, 1.0 / dt)


def _bad(counts: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in counts.items() if v is None or not np.isfinite(v) or v != 0}


def export_library(trajectories: Iterable[Trajectory], out_dir: str | Path,
                   fmt: Format = "npz", failed: Iterable[tuple[str, str]] = (),
                   robot: Any | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Write valid trajectories and the `library.csv` / `library.json` / `excluded.csv` indexes.

    Each file is re-read and re-validated with MuJoCo on `robot` (default: the robot the
    trajectory names, with its default definition); a file that fails, or whose stored counters
    are non-zero, is removed and listed as excluded. `failed` lists (id, reason) of sequences
    that never produced a trajectory. Returns (library, excluded), the same rows as the CSVs.
    """
    if fmt not in FORMATS:
        raise InputError(Path(out_dir), "format", f"unknown export format {fmt!r} (one of {FORMATS})")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _remove_previous(out_dir)
    robots: dict[str, Any] = {}
    kept, entries = [], []
    excluded = [{"id": sid, "status": "failed", "reason": reason} for sid, reason in failed]
    for traj in trajectories:
        row = {"id": traj.id, "robot": traj.robot, "text": traj.text,
               "frames": len(traj.q), "dt": traj.dt, "duration_s": len(traj.q) * traj.dt}
        bad = traj.violations
        if bad:
            reason = "; ".join(f"{k}={v}" for k, v in bad.items())
            excluded.append({**row, "status": "excluded", "reason": reason})
            continue
        rb = robot if robot is not None else robots.setdefault(traj.robot, _robot_named(traj.robot))
        if list(rb.joint_names) != list(traj.joint_names):
            raise InputError(traj.id, "joint_names", f"do not match robot {rb.name!r}'s joints")
        path = traj.save(out_dir / safe_name(traj.id), fmt, rb)
        written = file_validation(rb, path, fmt, traj.dt)
        if _bad(written):
            path.unlink()
            reason = "written file fails validation: " + "; ".join(
                f"{k}={v:g}" for k, v in _bad(written).items())
            excluded.append({**row, "status": "refused", "reason": reason})
            continue
        kept.append({**row, "status": "ok", "file": path.name,
                     **{f"validation.{k}": v for k, v in sorted(traj.validation.items())},
                     **{f"written.{k}": v for k, v in written.items()}})
        entries.append({"id": traj.id, "file": path.name, "text": traj.text, "frames": len(traj.q),
                        "dt": traj.dt,
                        "validation": traj.validation, "written": written})
    library = pd.DataFrame(kept, columns=None if kept else
                           ["id", "robot", "text", "frames", "dt", "duration_s", "status", "file"])
    excluded.sort(key=lambda row: row["id"])
    excl = pd.DataFrame(excluded, columns=["id", "robot", "text", "frames", "dt", "duration_s",
                                           "status", "reason"]).astype({"frames": "Int64"})
    csv_safe(library).to_csv(out_dir / "library.csv", index=False, lineterminator="\n", float_format="%.10g")
    csv_safe(excl).to_csv(out_dir / "excluded.csv", index=False, lineterminator="\n", float_format="%.10g")
    any_traj = next(iter(robots.values()), robot)
    meta = {"version": LIBRARY_VERSION, "format": fmt, "consumer": CONSUMERS[fmt],
            "robot": getattr(any_traj, "name", None) if any_traj is not None else None,
            "joint_names": list(any_traj.joint_names) if any_traj is not None else None,
            "rate_hz": (1.0 / library["dt"].iloc[0]) if len(library) else None,
            "validation_keys": list(VIOLATION_KEYS), "sequences": entries,
            "excluded": [{k: r.get(k) for k in ("id", "status", "reason")} for r in excluded]}
    (out_dir / "library.json").write_text(json.dumps(meta, indent=1, sort_keys=True, default=float)
                                          + "\n")
    return library, excl


def check_library(lib_dir: str | Path, robot: Any | None = None) -> pd.DataFrame:
    """Re-validate an exported library from its files alone (MuJoCo contacts, joint and velocity
    limits on the arrays as their consumer reads them). One row per listed sequence with the
    counters, the counters the index claims and `ok`."""
    lib_dir = Path(lib_dir)
    meta_path = lib_dir / "library.json"
    if not meta_path.is_file():
        raise InputError(meta_path, None, "not an exported library (no library.json)")
    try:
        meta = json.loads(meta_path.read_text())
        fmt, name = meta["format"], meta["robot"]
        entries = list(meta["sequences"])
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(meta_path, None, f"unreadable library index: {exc}") from None
    if fmt not in FORMATS:
        raise InputError(meta_path, "format", f"unknown export format {fmt!r}")
    if entries and robot is None:
        if not name:
            raise InputError(meta_path, "robot", "missing")
        robot = _robot_named(name)
    rows = []
    for entry in entries:
        path = lib_dir / str(entry["file"])
        if Path(str(entry["file"])).name != str(entry["file"]) or not path.is_file():
            rows.append({"id": entry["id"], "file": entry["file"], "ok": False, "error": "missing"})
            continue
        counts = file_validation(robot, path, fmt, float(entry["dt"]))
        claimed = entry.get("written", {})
        agree = all(float(claimed.get(k, np.nan)) == counts[k] for k in VIOLATION_KEYS)
        rows.append({"id": entry["id"], "file": entry["file"], **counts,
                     "ok": not _bad(counts) and agree,
                     "error": "" if agree else "counters differ from library.json"})
        rows[-1].update(_physics_row(robot, path, fmt, float(entry["dt"]), rows[-1]))
    return pd.DataFrame(rows, columns=["id", "file", *VIOLATION_KEYS, "ok", "error", *PHYSICS_CHECK_KEYS])


def _physics_row(robot: Any, path: Path, fmt: ExportFormat, dt: float, row: dict[str, Any]) -> dict[str, Any]:
    """The physics-valid rule on one file (`embody.export.control.physics_check`), folded into
    its check row: `ok` also needs physics-valid, `error` says why not."""
    from embody.export.control import physics_check
    if robot.spec.actuation is None:
        return {"physics_valid": None}
    out = physics_check(robot, path, read_joint_positions(path, fmt, robot.n_joints), dt)
    why = out.pop("physics_error", "") or ("" if out["physics_valid"] else "not physics-valid")
    errors = "; ".join(e for e in (row.get("error", ""), why) if e)
    return {**out, "ok": bool(row["ok"]) and bool(out["physics_valid"]), "error": errors}
