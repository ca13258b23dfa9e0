"""`tasks.recent`: a worker's own results of this run, read back without the store."""

from __future__ import annotations

import numpy as np

from embody.tasks import recent


def test_recall_gives_copies_of_what_was_published_in_the_same_session():
    arrays = {"q": np.arange(6.0).reshape(2, 3), "flag": np.array(True)}
    recent.remember("s1", "collide", "k1", arrays)
    arrays["q"][0, 0] = 99.0  # the publisher's array changes later: the memo does not
    got = recent.recall("s1", "collide", "k1")
    assert got["q"][0, 0] == 0.0 and got["flag"].shape == () and bool(got["flag"])
    got["q"][:] = -1.0  # a consumer's changes stay its own
    assert recent.recall("s1", "collide", "k1")["q"][1, 2] == 5.0
    assert recent.recall("s2", "collide", "k1") is None  # another run reads the store
    assert recent.recall("s1", "retarget", "k1") is None
    recent.forget("s1", "collide", "k1")
    assert recent.recall("s1", "collide", "k1") is None


def test_the_oldest_go_first_beyond_the_capacity(monkeypatch):
    monkeypatch.setattr(recent, "CAPACITY", 3 * 800)
    for i in range(4):
        recent.remember("cap", "step", f"k{i}", {"x": np.zeros(100)})  # 800 bytes each
    assert recent.recall("cap", "step", "k0") is None
    assert all(recent.recall("cap", "step", f"k{i}") is not None for i in (1, 2, 3))
    recent.remember("cap", "step", "big", {"x": np.zeros(1000)})  # over the capacity alone
    assert recent.recall("cap", "step", "big") is None
    for i in (1, 2, 3):
        recent.forget("cap", "step", f"k{i}")
