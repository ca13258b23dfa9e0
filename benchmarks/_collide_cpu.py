"""What `collision_cpu.py` and `collide_cpu.py` share: the default dataset's first N sequences,
the default body and collision config, one untimed warm-up call (numba's cached kernels load
once a process) and a CPU timer around one of `optimize`'s judge functions."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any, Callable

from embody.body import MannequinBody
from embody.collision import depth, optimize, part_volumes
from embody.config.collision import CollisionConfig
from embody.io import load
from embody.synth import default_dataset

ROOT = Path(__file__).resolve().parents[1]


def prepare(warm: Callable[..., Any], description: str = ""
            ) -> tuple[list[Path], MannequinBody, CollisionConfig]:
    """Parse `--data`/`--n`, build body and config, run `warm(motion, body, cfg)` once on the
    first sequence (untimed) and clear the judge's memo after it."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--data", default=str(ROOT / "data"))
    ap.add_argument("--n", type=int, default=24)
    args = ap.parse_args()
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))[: args.n]
    body, cfg = MannequinBody(), CollisionConfig()
    part_volumes(body)
    warm(load(paths[0]), body, cfg)
    depth._memo.clear()
    return paths, body, cfg


def time_judge(name: str) -> list[float]:
    """Replace `optimize.<name>` with a copy that adds its CPU seconds to the returned list's
    one element (reset it as you like)."""
    spent = [0.0]
    inner = getattr(optimize, name)

    def timed(*a: Any, **k: Any) -> Any:
        c = time.process_time()
        out = inner(*a, **k)
        spent[0] += time.process_time() - c
        return out

    setattr(optimize, name, timed)
    return spent
