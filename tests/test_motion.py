"""The canonical Motion type: validation and artifact round trip."""

from __future__ import annotations

import numpy as np
import pytest

from embody.errors import InputError
from embody.motion import Motion, MotionSource

RNG = np.random.default_rng(3)


def _motion(**kw):
    args = dict(pose=RNG.normal(size=(5, 55, 3)), transl=np.zeros((5, 3)), betas=np.zeros(10), fps=30,
                source=MotionSource("x.npz", "soke", "relative"), meta={"text": "hi"})
    args.update(kw)
    return Motion(**args)


def test_arrays_round_trip():
    m = _motion()
    back = Motion.from_arrays(m.to_arrays(), m.to_attrs())
    assert np.array_equal(back.pose, m.pose) and back.source == m.source and back.meta == m.meta
    assert back.fps == 30.0 and back.duration == pytest.approx(5 / 30)


@pytest.mark.parametrize("kw,field", [
    ({"pose": np.zeros((5, 54, 3))}, "pose"),
    ({"pose": np.zeros((1, 55, 3)), "transl": np.zeros((1, 3))}, "pose"),
    ({"transl": np.zeros((4, 3))}, "transl"),
    ({"betas": np.zeros(16)}, "betas"),
    ({"pose": np.full((5, 55, 3), np.nan)}, "pose"),
    ({"fps": 0}, "fps"),
    ({"fps": "fast"}, "fps"),
])
def test_validation_names_file_and_field(kw, field):
    with pytest.raises(InputError) as err:
        _motion(**kw)
    assert err.value.field == field and err.value.path == "x.npz"
    assert "\n" not in str(err.value) and "x.npz" in str(err.value)


def test_with_pose_keeps_everything_else():
    m = _motion()
    m2 = m.with_pose(np.zeros((5, 55, 3)))
    assert np.all(m2.pose == 0) and m2.source == m.source and m2.meta == m.meta
    m2.meta["x"] = 1
    assert "x" not in m.meta
