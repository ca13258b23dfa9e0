"""The scale benchmark's dataset: every sequence distinct, so a cold run computes each one.

`benchmarks/scale.py` builds N sequences as windows of a few generated ones; if two files
had the same bytes they would share content keys and a "cold" run would count cache hits as
throughput.
"""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

import numpy as np

from embody.io import load

ROOT = Path(__file__).resolve().parents[1]


def _scale():
    spec = importlib.util.spec_from_file_location("bench_scale", ROOT / "benchmarks" / "scale.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_windows_of_few_bases_are_distinct_and_cropped(tmp_path):
    scale = _scale()
    folder = scale.write_dataset(tmp_path / "d", n=7, frames=12, bases=3)
    files = sorted(folder.glob("seq_*.npz"))
    assert [f.name for f in files] == [f"seq_{i:05d}.npz" for i in range(7)]
    digests = {hashlib.sha256(f.read_bytes()).hexdigest() for f in files}
    assert len(digests) == 7
    motions = [load(f) for f in files]
    assert all(m.num_frames == 12 for m in motions)
    # sequence 3 is base 0 one frame later: the same motion, shifted (a real window)
    np.testing.assert_allclose(motions[3].pose[:-1], motions[0].pose[1:], atol=1e-6)
    assert not np.allclose(motions[3].pose, motions[0].pose)
    # reused when complete: nothing rewritten
    before = files[0].stat().st_mtime_ns
    scale.write_dataset(folder, n=7, frames=12, bases=3)
    assert files[0].stat().st_mtime_ns == before
