"""A small SMPL-X-format model file with random values, so the real SMPL-X loader path runs
in tests without the licensed model."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from embody.motion import JOINT_NAMES, PARENTS


def write_smplx(path: Path, seed: int = 0, drop: str | None = None, vertices: int = 400,
                faces: int = 600) -> Path:
    """A fake SMPL-X npz: 55-joint tree, (V,3,400) shape+expression basis, hand means.
    `drop` leaves one key out (to test the loader's errors)."""
    rng = np.random.default_rng(seed)
    v = vertices
    weights = rng.random((v, 55)) ** 8
    weights /= weights.sum(1, keepdims=True)
    regressor = rng.random((55, v))
    regressor /= regressor.sum(1, keepdims=True)
    kintree = np.stack([PARENTS, np.arange(55)]).astype(np.int64)
    kintree[0, 0] = 4294967295
    data = dict(v_template=rng.normal(size=(v, 3)) * 0.3, f=rng.integers(0, v, (faces, 3)),
                weights=weights, shapedirs=rng.normal(size=(v, 3, 400)) * 0.01,
                posedirs=rng.normal(size=(v, 3, 486)) * 1e-3, J_regressor=regressor,
                kintree_table=kintree, hands_meanl=rng.normal(size=45) * 0.2,
                hands_meanr=rng.normal(size=45) * 0.2,
                joint2num=np.array({n: i for i, n in enumerate(JOINT_NAMES)}, dtype=object))
    if drop:
        del data[drop]
    np.savez(path, **data)
    return path
