"""The report's plots drawn side by side in helper processes (`embody.report.drawing`): the same
files as drawn one after another, in order, and a plot that fails in a helper raises here."""

from __future__ import annotations

import numpy as np
import pytest

from embody.report import figures
from embody.report.drawing import MIN_PARALLEL, draw


def _jobs(folder, n):
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        tracks = {"reference": rng.normal(size=(40, 2, 3)), "ik": rng.normal(size=(40, 2, 3))}
        out.append((figures.wrist_tracks, (tracks, 30.0, folder / f"w{i}.png"),
                    {"title": f"seq{i}"}))
    return out


def test_helpers_draw_the_same_files_as_one_process(tmp_path):
    n = MIN_PARALLEL
    side = draw(_jobs(tmp_path / "side", n), processes=2)
    alone = draw(_jobs(tmp_path / "alone", n), processes=1)
    assert side == [tmp_path / "side" / f"w{i}.png" for i in range(n)]  # in the jobs' order
    for a, b in zip(side, alone):
        assert a.read_bytes() == b.read_bytes() and a.stat().st_size > 1000


def test_a_plot_that_fails_in_a_helper_raises_here(tmp_path):
    jobs = _jobs(tmp_path, 2)
    bad = dict(jobs[1][1][0], ik=np.zeros((3, 2)))  # wrong shape: the plot raises
    jobs[1] = (figures.wrist_tracks, (bad, 30.0, tmp_path / "bad.png"), {"title": "bad"})
    with pytest.raises(ValueError):
        draw(jobs, processes=2)  # the second share is the helper's; redrawn here, it raises
    assert (tmp_path / "w0.png").is_file() and not (tmp_path / "bad.png").exists()
