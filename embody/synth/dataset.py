"""Writing synthetic datasets: `seq_000.npz`, ... plus a `path,text` manifest."""

from __future__ import annotations

import csv
import io
import shutil
import tempfile
from pathlib import Path

from embody.errors import InputError
from embody.io import save
from embody.io.npzfile import write_atomic
from embody.synth.generator import GENERATOR_VERSION, generate_sequence
from embody.synth.kinematics import ArmIK

DEFAULT_N = 24
DEFAULT_SEED = 0


def generate_dataset(out_dir: str | Path, n: int = DEFAULT_N, seed: int = DEFAULT_SEED) -> list[Path]:
    """Write `n` sequences of `seed` into `out_dir`; the same (n, seed) gives the same bytes."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, None, "output exists and is not a directory")
    if n < 1:
        raise InputError(out_dir, "n", f"need at least 1 sequence, got {n}")
    out_dir.mkdir(parents=True, exist_ok=True)
    ik = ArmIK()
    paths, rows = [], []
    for index in range(n):
        motion = generate_sequence(seed, index, ik)
        path = save(motion, out_dir / f"seq_{index:03d}.npz")
        paths.append(path)
        rows.append((path.name, motion.meta["text"]))
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows([("path", "text"), *rows])
    write_atomic(out_dir / "manifest.csv", text.getvalue().encode())
    return paths


def _generator_of(folder: Path) -> str | None:
    """The generator version recorded in the folder's first sequence, None when unreadable."""
    from embody.io import load
    try:
        return load(folder / "seq_000.npz").meta.get("generator")
    except Exception:  # a half-copied or foreign folder: treat it as stale
        return None


def default_dataset(data_dir: str | Path, n: int = DEFAULT_N, seed: int = DEFAULT_SEED) -> Path:
    """`data_dir/synth-n<n>-s<seed>/`, generated on first use, and again when the folder was made
    by another generator version (a user upgrading gets the corrected signs, not a silent reuse
    of the old ones; downstream steps are keyed on content, so only what changed is recomputed).

    Generated in a temporary sibling folder and renamed into place, so a crash never leaves a
    half dataset and concurrent first uses agree on one complete copy; a stale copy is first
    moved aside (and removed), never overwritten in place.
    """
    data_dir = Path(data_dir)
    target = data_dir / f"synth-n{n}-s{seed}"
    if target.is_dir() and _generator_of(target) == GENERATOR_VERSION:
        return target
    data_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=data_dir))
    stale = None
    try:
        generate_dataset(tmp, n=n, seed=seed)
        if target.is_dir() and _generator_of(target) != GENERATOR_VERSION:
            stale = Path(tempfile.mkdtemp(prefix=f".{target.name}.stale.", dir=data_dir))
            try:
                target.rename(stale / "old")
            except OSError:  # another process moved it first
                pass
        tmp.rename(target)
    except OSError:
        if not target.is_dir() or _generator_of(target) != GENERATOR_VERSION:
            raise  # a real failure, not a lost race with another process
    finally:
        for leftover in (tmp, stale):
            if leftover is not None and leftover.exists():
                shutil.rmtree(leftover, ignore_errors=True)
    return target
