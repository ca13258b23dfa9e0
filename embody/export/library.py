"""The exported trajectory library: one file per validated sequence plus `library.csv` and
`library.json` indexes.

A trajectory is exported only if the file as written passes validation: it is read back the way
its consumer reads it (`embody.export.formats`, float32 cast included for BeyondMimic) and that
array is checked with MuJoCo and the robot's limits (`retarget.validation`): no joint-limit or
velocity-limit violations and no self-collision frames at any sample. The counters the run
stored must agree. The rest are listed in `excluded.csv` with the reason, so a user can see what
the library is missing and why. `check_library` re-validates a received library from its files,
treating every byte of it as hostile (see docs/security.md): bounded reads, paths confined to the
library, the rate taken from each file, non-finite values refused.

Every file and index is written whole (temp, fsync, rename): a failed export (a full disk) removes
what it wrote and raises, so no truncated file and no index naming missing files is left.
"""

from __future__ import annotations

import errno
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pandas as pd

from embody.config.io import IOConfig
from embody.csvsafe import csv_safe
from embody.errors import ConfigError, EmbodyError, InputError
from embody.report.paths import safe_name
from embody.export.atomic import sync_dir, write_atomic
from embody.export.control import PHYSICS_CHECK_KEYS
from embody.export.formats import (CONSUMERS, FORMATS, ExportFormat, Layout, open_regular,
                                   read_trajectory, root_pose, trajectory_bytes, write_trajectory,
                                   companion_bytes, companion_files)
from embody.retarget.validation import VALIDATION_KEYS

#: Validation counters that must be zero for a trajectory to be exported.
VIOLATION_KEYS = VALIDATION_KEYS
Format = ExportFormat
LIBRARY_VERSION = 2
#: The rate of a file that states none (BeyondMimic csv) when library.json does not either:
#: the control rate every export is written at (README, "Export formats").
DOCUMENTED_RATE_HZ = 50.0
#: Largest library.json read (bytes); ~1 KB per sequence, so ~60,000 sequences.
MAX_INDEX_BYTES = 64 << 20
#: Relative tolerance between two statements of one rate (GMR's integer fps of 1/dt).
RATE_TOLERANCE = 1e-6
_INDEXES = ("library.json", "library.csv", "excluded.csv")
_ROBOT_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


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
    #: (T,) each sample's time (s) on the source motion's timeline: k·dt unless the torque and
    #: ZMP limits slowed the motion down (`retarget.dynamics_limits.retime_dynamics`); None: k·dt.
    source_time: np.ndarray | None = None

    def __post_init__(self) -> None:
        q = np.asarray(self.q, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != len(self.joint_names):
            raise InputError(self.id, "q", f"expected (T, {len(self.joint_names)}), got {q.shape}")
        if not (math.isfinite(self.dt) and self.dt > 0):
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
        meta = {"id": self.id, "robot": self.robot, "text": self.text, "validation": self.validation}
        if self.source_time is not None:
            meta["source_time"] = np.asarray(self.source_time, dtype=np.float64)
        return Layout(self.joint_names, self.dt, pos, quat, meta, control)

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
                   validation=json.loads(str(data.get("validation", "{}"))),
                   source_time=np.asarray(data["source_time"], dtype=np.float64) if "source_time" in data else None)


def _previous_files(out_dir: Path) -> list[Path]:
    """The files a previous export listed (plain names inside `out_dir` only)."""
    index = out_dir / "library.csv"
    if not index.is_file() or index.is_symlink():
        return []
    try:
        names = pd.read_csv(index, dtype=str, keep_default_na=False).get("file", [])
    except Exception:  # an unreadable index names nothing; its files stay
        return []
    files = [out_dir / n for n in names if n and Path(n).name == n and n not in (".", "..")]
    # a csv may be BeyondMimic's, with its side file
    return files + [c for f in files if f.suffix == ".csv" for c in companion_files(f, "beyondmimic")]


def _robot_named(name: str) -> Any:
    from embody.config.robot import RobotConfig
    from embody.robot import load_robot

    return load_robot(RobotConfig(name=name))


def _rate_within(rate: float, limits: IOConfig) -> bool:
    return math.isfinite(rate) and limits.min_fps <= rate <= limits.max_fps


def _same_rate(a: float, b: float) -> bool:
    return math.isfinite(a) and math.isfinite(b) and abs(a - b) <= RATE_TOLERANCE * max(abs(a), abs(b))


def file_validation(robot: Any, path: Path, fmt: ExportFormat, dt: float | None,
                    limits: IOConfig | None = None, side: Path | None = None) -> dict[str, float]:
    """Validation counters of an exported file's joint array, read as its consumer reads it, at
    the rate the file states (which must agree with `dt` when both are given)."""
    return _file_counts(robot, path, fmt, dt, limits, side)[0]


def _file_counts(robot: Any, path: Path, fmt: ExportFormat, dt: float | None,
                 limits: IOConfig | None, side: Path | None = None
                 ) -> tuple[dict[str, float], int, np.ndarray, float]:
    """(validation counters, frames, joint array, rate) of an exported file; see
    `file_validation`."""
    from embody.retarget.validation import validation_counts

    limits = limits or IOConfig()
    read = read_trajectory(path, fmt, robot.joint_names, max_frames=limits.max_frames, side=side)
    rate = read.rate_hz if read.rate_hz is not None else (
        1.0 / dt if dt is not None else DOCUMENTED_RATE_HZ)
    if not _rate_within(rate, limits):
        raise InputError(path, "rate", f"{rate:g} Hz is outside io.min_fps..io.max_fps "
                                       f"({limits.min_fps:g}..{limits.max_fps:g})")
    if dt is not None and not _same_rate(rate, 1.0 / dt):
        raise InputError(path, "rate", f"the file says {rate:g} Hz, library.json {1.0 / dt:g} Hz")
    return validation_counts(robot, read.q, rate), len(read.q), read.q, rate


def _bad(counts: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in counts.items() if v is None or not np.isfinite(v) or v != 0}


def _unfit(traj: Trajectory, limits: IOConfig) -> str:
    """Why `traj` cannot become a file `export --check` accepts ('' when it can)."""
    if not len(traj.q):
        return "no frames"
    if len(traj.q) > limits.max_frames:
        return f"{len(traj.q)} frames exceeds io.max_frames={limits.max_frames}"
    if not np.isfinite(traj.q).all():
        return "non-finite joint positions (NaN or inf)"
    if not _rate_within(1.0 / traj.dt, limits):
        return (f"rate {1.0 / traj.dt:g} Hz is outside io.min_fps..io.max_fps "
                f"({limits.min_fps:g}..{limits.max_fps:g})")
    return ""


def export_library(trajectories: Iterable[Trajectory], out_dir: str | Path,
                   fmt: Format = "npz", failed: Iterable[tuple[str, str]] = (),
                   robot: Any | None = None, limits: IOConfig | None = None
                   ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Write valid trajectories and the `library.csv` / `library.json` / `excluded.csv` indexes.

    Each file is written to a temp file, re-read and re-validated with MuJoCo on `robot`
    (default: the robot the trajectory names, with its default definition) and renamed into
    place only if it passes; one that fails, or whose stored counters are non-zero, or that
    `check_library` would refuse (non-finite, over `limits.max_frames`, rate outside the `io`
    bounds), is listed as excluded. `failed` lists (id, reason) of sequences that never
    produced a trajectory. The previous export's files and indexes are removed first and
    library.json is written last. If a write fails (a full disk) everything this export wrote
    is removed and an `EmbodyError` names the folder (any other error also removes them).
    Returns (library, excluded), the same rows as the CSVs.
    """
    if fmt not in FORMATS:
        raise InputError(Path(out_dir), "format", f"unknown export format {fmt!r} (one of {FORMATS})")
    limits = limits or IOConfig()
    out_dir = Path(out_dir)
    written: list[Path] = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        previous = _previous_files(out_dir)
        for name in _INDEXES:  # the index goes first: no index ever names a missing file
            (out_dir / name).unlink(missing_ok=True)
        for path in previous:
            path.unlink(missing_ok=True)
        library, excl = _write_library(trajectories, out_dir, fmt, failed, robot, limits, written)
        sync_dir(out_dir)
    except BaseException as exc:  # a failed export leaves none of its files (Ctrl-C included)
        for path in written:
            path.unlink(missing_ok=True)
        if not isinstance(exc, OSError):
            raise
        reason = "no space left on device" if exc.errno == errno.ENOSPC else (
            exc.strerror or str(exc))
        raise EmbodyError(f"{out_dir}: cannot write the library ({reason}); the files it had "
                          "written are removed") from None
    return library, excl


def _write_library(trajectories: Iterable[Trajectory], out_dir: Path, fmt: Format,
                   failed: Iterable[tuple[str, str]], robot: Any | None, limits: IOConfig,
                   written: list[Path]) -> tuple[pd.DataFrame, pd.DataFrame]:
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
        unfit = _unfit(traj, limits)
        if unfit:
            excluded.append({**row, "status": "refused", "reason": unfit})
            continue
        rb = robot if robot is not None else robots.setdefault(traj.robot, _robot_named(traj.robot))
        if list(rb.joint_names) != list(traj.joint_names):
            raise InputError(traj.id, "joint_names", f"do not match robot {rb.name!r}'s joints")
        suffix, data = trajectory_bytes(fmt, traj.q, traj.layout(rb))
        path = out_dir / (safe_name(traj.id) + suffix)
        companions = companion_bytes(fmt, traj.q, traj.layout(rb), path)
        for side_path, side_data in companions:  # first: the file's check reads them
            write_atomic(side_path, side_data)
            written.append(side_path)
        side = companions[0][0] if companions else None
        counts: dict[str, float] = {}
        refusal: list[str] = []

        def accept(tmp: Path, rb: Any = rb, traj: Trajectory = traj, side: Path | None = side) -> bool:
            try:
                counts.update(file_validation(rb, tmp, fmt, traj.dt, limits, side))
            except InputError as exc:
                refusal.append(exc.message)
                return False
            return not _bad(counts)

        if not write_atomic(path, data, accept):
            for side_path, _ in companions:
                side_path.unlink(missing_ok=True)
            reason = "written file fails validation: " + (refusal[0] if refusal else "; ".join(
                f"{k}={v:g}" for k, v in _bad(counts).items()))
            excluded.append({**row, "status": "refused", "reason": reason})
            continue
        written.append(path)
        kept.append({**row, "status": "ok", "file": path.name,
                     **{f"validation.{k}": v for k, v in sorted(traj.validation.items())},
                     **{f"written.{k}": v for k, v in counts.items()}})
        entries.append({"id": traj.id, "file": path.name, "text": traj.text, "frames": len(traj.q),
                        **({"companion_files": [p.name for p, _ in companions]} if companions else {}),
                        "dt": traj.dt,
                        "validation": traj.validation, "written": counts})
    library = pd.DataFrame(kept, columns=None if kept else
                           ["id", "robot", "text", "frames", "dt", "duration_s", "status", "file"])
    excluded.sort(key=lambda row: row["id"])
    excl = pd.DataFrame(excluded, columns=["id", "robot", "text", "frames", "dt", "duration_s",
                                           "status", "reason"]).astype({"frames": "Int64"})
    any_traj = next(iter(robots.values()), robot)
    meta = {"version": LIBRARY_VERSION, "format": fmt, "consumer": CONSUMERS[fmt],
            "robot": getattr(any_traj, "name", None) if any_traj is not None else None,
            "joint_names": list(any_traj.joint_names) if any_traj is not None else None,
            "rate_hz": (1.0 / library["dt"].iloc[0]) if len(library) else None,
            "validation_keys": list(VIOLATION_KEYS), "sequences": entries,
            "excluded": [{k: r.get(k) for k in ("id", "status", "reason")} for r in excluded]}
    for name, text in (
            ("library.csv", csv_safe(library).to_csv(index=False, lineterminator="\n",
                                                     float_format="%.10g")),
            ("excluded.csv", csv_safe(excl).to_csv(index=False, lineterminator="\n",
                                                   float_format="%.10g")),
            ("library.json", json.dumps(meta, indent=1, sort_keys=True, default=float) + "\n")):
        write_atomic(out_dir / name, text.encode("utf-8"))  # library.json last: the library is whole
        written.append(out_dir / name)
    return library, excl


@dataclass(frozen=True)
class _Entry:
    """One `sequences` entry of library.json, its types checked."""

    id: str
    file: str
    dt: float | None
    frames: int | None
    written: dict[str, Any]


def _number(value: Any) -> float | None:
    """A JSON number as a finite float; None for anything else (bools, text, 1e999, 10**400)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _plain_name(name: Any) -> bool:
    """A file name directly inside the library: no separators, no `.`/`..`, printable."""
    return (isinstance(name, str) and 0 < len(name) <= 255 and name not in (".", "..")
            and "/" not in name and "\\" not in name and name.isprintable())


def _entry(entry: Any, i: int, where: Path) -> _Entry:
    key = f"sequences[{i}]"
    if not isinstance(entry, dict):
        raise InputError(where, key, f"expected an object, got {type(entry).__name__}")
    if not isinstance(entry.get("id"), str) or not entry["id"]:
        raise InputError(where, f"{key}.id", "missing or not text")
    if "file" not in entry:
        raise InputError(where, f"{key}.file", "missing")
    if not _plain_name(entry["file"]):
        raise InputError(where, f"{key}.file", "not a file name inside the library")
    dt = entry.get("dt")
    if dt is not None and not (_number(dt) or 0) > 0:
        raise InputError(where, f"{key}.dt", f"must be a number > 0, got {dt!r:.40}")
    frames = entry.get("frames")
    if frames is not None and not (isinstance(frames, int) and not isinstance(frames, bool)):
        raise InputError(where, f"{key}.frames", f"must be an integer, got {frames!r:.40}")
    written = entry.get("written", {})
    if not isinstance(written, dict):
        raise InputError(where, f"{key}.written", "expected an object")
    return _Entry(entry["id"], entry["file"], _number(dt), frames, written)


def _read_index(path: Path) -> dict[str, Any]:
    """library.json as a dict, read within MAX_INDEX_BYTES (a regular file, not a link)."""
    with open_regular(path, MAX_INDEX_BYTES) as fh:
        raw = fh.read()
    try:
        meta = json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        reason = "nested too deeply" if isinstance(exc, RecursionError) else " ".join(str(exc).split())
        raise InputError(path, None, f"unreadable library index: {reason[:200]}") from None
    if not isinstance(meta, dict):
        raise InputError(path, None, "expected a JSON object")
    return meta


def _index_robot(meta: dict[str, Any], path: Path, robot: Any | None) -> Any:
    """The robot to validate against: `robot`, else the one library.json names."""
    if robot is None:
        name = meta.get("robot")
        if not isinstance(name, str) or not _ROBOT_NAME.match(name) or set(name) == {"."}:
            raise InputError(path, "robot", "missing or not a robot name ([A-Za-z0-9_.-]+)")
        try:
            robot = _robot_named(name)
        except ConfigError as exc:
            raise InputError(path, "robot", exc.message) from None
    names = meta.get("joint_names")
    if names is not None and names != list(robot.joint_names):
        raise InputError(path, "joint_names", f"differ from robot {robot.name!r}'s joints")
    return robot


def check_library(lib_dir: str | Path, robot: Any | None = None,
                  limits: IOConfig | None = None) -> pd.DataFrame:
    """Re-validate an exported library from its files alone (MuJoCo contacts, joint and velocity
    limits at every sample of the arrays as their consumer reads them, at the rate each file
    states). One row per listed sequence with the counters, whether they agree with the ones
    library.json claims, and `ok`.

    Anything that is not a well-formed library is an `InputError` naming the file and field:
    library.json or a file that is not a regular file in the folder (links refused), over the
    size/frame bounds (`limits.max_frames`), unparsable, with non-finite values, a rate outside
    `io.min_fps..io.max_fps` or one that disagrees with library.json, or an index entry of the
    wrong shape.
    """
    limits = limits or IOConfig()
    root = Path(lib_dir)
    meta_path = root / "library.json"
    if not root.is_dir() or not (meta_path.is_file() or meta_path.is_symlink()):
        raise InputError(meta_path, None, "not an exported library (no library.json)")
    root = root.resolve()
    meta_path = root / "library.json"
    meta = _read_index(meta_path)
    fmt, sequences = meta.get("format"), meta.get("sequences")
    if not isinstance(fmt, str) or fmt not in FORMATS:
        raise InputError(meta_path, "format", f"unknown export format {fmt!r:.40} (one of {FORMATS})")
    if not isinstance(sequences, list):
        raise InputError(meta_path, "sequences", "missing or not a list")
    entries = [_entry(e, i, meta_path) for i, e in enumerate(sequences)]
    stated = meta.get("rate_hz")
    rate_hz = _number(stated)
    if stated is not None and (rate_hz is None or not _rate_within(rate_hz, limits)):
        raise InputError(meta_path, "rate_hz", f"must be a number within io.min_fps..io.max_fps, "
                                               f"got {stated!r:.40}")
    for i, e in enumerate(entries):
        if rate_hz is not None and e.dt is not None and not _same_rate(rate_hz, 1.0 / e.dt):
            raise InputError(meta_path, f"sequences[{i}].dt", f"says {1.0 / e.dt:g} Hz, rate_hz "
                                                              f"{rate_hz:g} Hz")
    if entries:
        robot = _index_robot(meta, meta_path, robot)
    rows = []
    done: dict[tuple[str, float | None], tuple[dict[str, Any], int]] = {}
    for e in entries:
        dt = e.dt if e.dt is not None else (1.0 / rate_hz if rate_hz is not None else None)
        if (e.file, dt) not in done:  # a file listed many times is read and checked once
            counts, frames, q, rate = _file_counts(robot, root / e.file, fmt, dt, limits)  # type: ignore[arg-type]
            done[(e.file, dt)] = ({**counts, **_physics(robot, root / e.file, q, rate)}, frames)
        counts, frames = done[(e.file, dt)]
        agree = all(_number(e.written.get(k)) == counts[k] for k in VIOLATION_KEYS)
        error = "" if agree else "counters differ from library.json"
        if e.frames is not None and e.frames != frames:
            error = f"{frames} frames, library.json says {e.frames}"
        physics_ok = counts.get("physics_valid") is not False
        why = counts.get("physics_error", "") or ("" if physics_ok else "not physics-valid")
        rows.append({"id": e.id, "file": e.file, **{k: v for k, v in counts.items() if k != "physics_error"},
                     "ok": not _bad({k: counts[k] for k in VIOLATION_KEYS}) and not error and physics_ok,
                     "error": "; ".join(x for x in (error, why) if x)})
    return pd.DataFrame(rows, columns=["id", "file", *VIOLATION_KEYS, "ok", "error", *PHYSICS_CHECK_KEYS])


def _physics(robot: Any, path: Path, q: np.ndarray, rate: float) -> dict[str, Any]:
    """The physics-valid rule on one file's array (`embody.export.control.physics_check`):
    its commands replayed in MuJoCo with the robot's actuation; `physics_valid` None for a
    robot without an `actuation` section."""
    from embody.export.control import physics_check
    if robot.spec.actuation is None:
        return {"physics_valid": None}
    return physics_check(robot, path, q, 1.0 / rate)
