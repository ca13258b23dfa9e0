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
from embody.synth.generator import generate_sequence
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


def default_dataset(data_dir: str | Path, n: int = DEFAULT_N, seed: int = DEFAULT_SEED) -> Path:
    """`data_dir/synth-n<n>-s<seed>/`, generated on first use.

    Generated in a temporary sibling folder and renamed into place, so a crash never leaves a
    half dataset and concurrent first uses agree on one complete copy.
    """
    data_dir = Path(data_dir)
    target = data_dir / f"synth-n{n}-s{seed}"
    if target.is_dir():
        return target
    data_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=data_dir))
    try:
        generate_dataset(tmp, n=n, seed=seed)
        tmp.rename(target)
    except OSError:
        if not target.is_dir():  # a real failure, not a lost race with another process
            raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target
