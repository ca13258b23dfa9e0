"""The exported trajectory library: one file per validated sequence plus a `library.csv` index.

A trajectory is exported only if it passed validation: no joint-limit or velocity-limit
violations and no self-collision frames. The rest are listed in `excluded.csv` with the reason,
so a user can see what the library is missing and why.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal

import numpy as np
import pandas as pd

from embody.errors import InputError

from embody.retarget.validation import VALIDATION_KEYS

#: Validation counters that must be zero for a trajectory to be exported.
VIOLATION_KEYS = VALIDATION_KEYS
Format = Literal["npz", "csv"]


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

    def save_npz(self, path: Path) -> Path:
        """An `np.load`-able npz with fixed zip timestamps: equal trajectories, equal bytes."""
        arrays = {"q": self.q, "dt": np.float64(self.dt), "joint_names": np.array(self.joint_names),
                  "source_id": np.array(self.id), "robot": np.array(self.robot),
                  "text": np.array(self.text),
                  "validation": np.array(json.dumps(self.validation, sort_keys=True,
                                                    default=float))}
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, value in arrays.items():
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                zf.writestr(info, buf.getvalue())
        return path

    def save_csv(self, path: Path) -> Path:
        """Time column then one column per joint (radians), one row per control step."""
        frame = pd.DataFrame(self.q, columns=list(self.joint_names))
        frame.insert(0, "time", np.arange(len(self.q)) * self.dt)
        frame.to_csv(path, index=False, lineterminator="\n", float_format="%.9g")
        return path

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


def safe_name(sid: str) -> str:
    """A sequence id as a file name; ids with slashes or spaces get a short hash so that
    "a/b" and "a_b" stay distinct."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in sid)
    if safe == sid:
        return sid
    return f"{safe}-{hashlib.sha1(sid.encode('utf-8')).hexdigest()[:8]}"


def _remove_previous(out_dir: Path) -> None:
    """Delete the files a previous export listed, so a re-export never leaves stale ones."""
    index = out_dir / "library.csv"
    if index.is_file():
        for name in pd.read_csv(index, dtype=str, keep_default_na=False).get("file", []):
            if name and Path(name).name == name:
                (out_dir / name).unlink(missing_ok=True)


def export_library(trajectories: Iterable[Trajectory], out_dir: str | Path,
                   fmt: Format = "npz", failed: Iterable[tuple[str, str]] = ()
                   ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Write valid trajectories and the `library.csv` / `excluded.csv` indexes.

    `failed` lists (id, reason) of sequences that never produced a trajectory; they are
    excluded too. Returns (library, excluded), the same rows as the CSV files.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _remove_previous(out_dir)
    kept = []
    excluded = [{"id": sid, "status": "failed", "reason": reason} for sid, reason in failed]
    for traj in trajectories:
        row = {"id": traj.id, "robot": traj.robot, "text": traj.text,
               "frames": len(traj.q), "dt": traj.dt, "duration_s": len(traj.q) * traj.dt}
        bad = traj.violations
        if bad:
            reason = "; ".join(f"{k}={v}" for k, v in bad.items())
            excluded.append({**row, "status": "excluded", "reason": reason})
            continue
        name = f"{safe_name(traj.id)}.{fmt}"
        (traj.save_npz if fmt == "npz" else traj.save_csv)(out_dir / name)
        kept.append({**row, "status": "ok", "file": name,
                     **{f"validation.{k}": v for k, v in sorted(traj.validation.items())}})
    library = pd.DataFrame(kept, columns=None if kept else
                           ["id", "robot", "text", "frames", "dt", "duration_s", "status", "file"])
    excluded.sort(key=lambda row: row["id"])
    excl = pd.DataFrame(excluded, columns=["id", "robot", "text", "frames", "dt", "duration_s",
                                           "status", "reason"]).astype({"frames": "Int64"})
    library.to_csv(out_dir / "library.csv", index=False, lineterminator="\n", float_format="%.10g")
    excl.to_csv(out_dir / "excluded.csv", index=False, lineterminator="\n", float_format="%.10g")
    return library, excl
