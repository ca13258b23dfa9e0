"""The paper's metrics and Tables I/II on hand-computed toy numbers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from embody.collision.metrics import accel_mse, pose_mse, sequence_metrics, table1, table2


def test_sequence_metrics_by_hand():
    x0 = np.zeros((4, 2, 3))
    x = x0.copy()
    x[1, 0, 0] = 1.0      # one frame moved by 1 rad on one axis
    x[2, 1, 2] = 2.0      # another by 2 rad
    assert pose_mse(x, x0) == pytest.approx((1 + 4) / 4)
    # second differences: frame 1 → −2 on [0,0] and +2 on [1,2]; frame 2 → +1 and −4
    acc1 = 4 + 4          # (−2)² + 2²
    acc2 = 1 + 16         # 1² + (−4)²
    assert accel_mse(x) == pytest.approx((acc1 + acc2) / 2)
    m = sequence_metrics(x0, x, energy_before=0.5, energy_after=0.1, runtime_s=2.0, steps=7)
    assert m["improved"] and not m["no_collision"]
    assert m["reduction_pct"] == pytest.approx(80.0)
    assert m["daccel_mse"] == pytest.approx(12.5) and m["frames"] == 4 and m["steps"] == 7
    z = sequence_metrics(x0, x0, 0.0, 0.0, 0.1, 0)
    assert z["no_collision"] and not z["improved"] and z["reduction_pct"] == 0.0


def toy() -> pd.DataFrame:
    rows = [  # before, after, runtime
        (1.0, 0.0, 1.0), (2.0, 1.0, 2.0), (4.0, 4.0, 3.0), (0.0, 0.0, 6.0)]
    out = []
    for i, (b, a, rt) in enumerate(rows):
        x0 = np.zeros((3, 1, 3))
        x = x0 + 0.1 * i
        out.append(sequence_metrics(x0, x, b, a, rt, 10))
    return pd.DataFrame(out)


def test_table1_by_hand():
    t = table1(toy())["value"]
    assert t["Sequences (colliding / total)"] == "3 / 4" and t["No collision"] == 1
    assert t["L_col before (mean)"] == pytest.approx(7 / 3)
    assert t["L_col before (median)"] == pytest.approx(2.0)
    assert t["L_col after (mean)"] == pytest.approx(5 / 3)
    assert t["L_col after (median)"] == pytest.approx(1.0)
    assert t["Improved n/N (%)"] == "2/3 (66.7%)"
    assert t["Reduction (median, %)"] == pytest.approx(50.0)     # 100, 50, 0
    assert t["Reduction (mean, %)"] == pytest.approx(50.0)
    assert t["Pose MSE (median)"] == pytest.approx(3 * 0.1 ** 2)  # sequence 1: 3 dims × 0.01
    assert t["ΔAccel MSE (median)"] == pytest.approx(0.0)
    assert t["Runtime (mean, s)"] == pytest.approx(3.0)


def test_table2_by_hand():
    df = toy()
    t = table2({"Collision only": df, "+ Closeness": df.iloc[:2]})
    assert list(t.columns) == ["N", "Succ. (%)", "Red. (%)", "Pose MSE", "ΔAccel MSE", "Time (s)"]
    assert t.loc["Collision only", "N"] == 3
    assert t.loc["Collision only", "Succ. (%)"] == pytest.approx(200 / 3)
    assert t.loc["+ Closeness", "Succ. (%)"] == pytest.approx(100.0)
    assert t.loc["+ Closeness", "Red. (%)"] == pytest.approx(75.0)
    assert t.loc["+ Closeness", "Time (s)"] == pytest.approx(1.5)


def test_table1_depth_rows_before_and_after():
    from embody.collision.depth import depth_metrics
    from embody.report.assemble import table1_slot

    df = toy()
    per_seq = [depth_metrics(np.array(b), np.array(a)) for b, a in (
        ([0.0, 0.006, 0.003], [0.0, 0.001, 0.0]), ([0.004, 0.0, 0.0], [0.0, 0.0, 0.0]),
        ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]))]
    df = pd.concat([df, pd.DataFrame(per_seq)], axis=1)
    t = table1(df)["value"]
    assert t["Frames deeper than 2 mm (before)"] == 3 and t["Frames deeper than 2 mm (after)"] == 0
    assert t["Frames deeper than 5 mm (before)"] == 1 and t["Frames deeper than 5 mm (after)"] == 0
    assert t["Max depth mm (before)"] == pytest.approx(6.0)
    assert t["Max depth mm (after)"] == pytest.approx(1.0)
    # medians over the penetrating sequences of their per-sequence medians: 4.5 and 4
    assert t["Median depth mm of penetrating frames (before)"] == pytest.approx(4.25)
    assert t["Median depth mm of penetrating frames (after)"] == pytest.approx(1.0)
    assert table1_slot("Max depth mm (after)") == ("Max depth mm", "After")
    assert table1_slot("Frames deeper than 5 mm (before)") == ("Frames deeper than 5 mm", "Before")
