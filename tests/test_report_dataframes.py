"""`write_report` from plain DataFrames (no store): tables, summary and page for in-memory data."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from embody.collision.metrics import sequence_metrics, table1
from embody.report import RunData, write_report
from embody.report.assemble import number, table1_slot


def _data() -> RunData:
    rng = np.random.default_rng(0)
    ids = ["s0", "s1", "s2", "s3"]
    coll = {}
    for k, sid in enumerate(ids[:3]):
        x0 = rng.normal(size=(12, 55, 3))
        x = x0 + 0.01 * k * rng.normal(size=x0.shape)
        coll[sid] = sequence_metrics(x0, x, energy_before=[0.0, 2.0, 1.0][k],
                                     energy_after=[0.0, 0.5, 1.2][k], runtime_s=1.0 + k, steps=50)
    retarget = pd.DataFrame({"wrist_pos_err_mm": [10.0, 20.0, 30.0],
                             "wrist_rot_err_deg": [1.0, 2.0, 3.0],
                             "joint_limit_violations": [0.0, 0.0, 0.0],
                             "velocity_violations": [0.0, 1.0, 0.0],
                             "self_collision_frames": [0.0, 0.0, 2.0],
                             "torque_viol": [0.0, 0.0, 0.0]}, index=ids[:3])
    sequences = pd.DataFrame({"status": ["ok", "ok", "ok", "failed"],
                              "error": ["", "", "", "collide: boom"], "text": ["a", "b", "c", "d"]},
                             index=pd.Index(ids, name="id"))
    data = RunData("mem", sequences, collision=pd.DataFrame.from_dict(coll, orient="index"),
                   retarget=retarget)
    # The pipeline's metrics step: validation counters of the final trajectories.
    data.other["metrics"] = retarget[["joint_limit_violations", "velocity_violations",
                                      "self_collision_frames", "torque_viol"]].copy()
    return data


def test_report_from_dataframes(tmp_path) -> None:
    data = _data()
    paths = write_report(data, tmp_path / "r")
    # Table II only exists with an ablation; the verdicts come first.
    assert list(paths.tables) == ["verdicts", "table1_collision", "table3_retargeting"]
    verdicts = pd.read_csv(paths.tables["verdicts"]["csv"], keep_default_na=False).set_index("Verdict")
    assert verdicts.loc["Processed ok", "Sequences"] == "3/4"
    assert verdicts.loc["Export-valid", "Sequences"] == "1/4"  # s1 too fast, s2 self-collides
    assert verdicts.loc["Critic-accepted", "Sequences"] == "n/a"  # no critic

    t1 = pd.read_csv(paths.tables["table1_collision"]["csv"]).set_index("Metric")
    for label, value in table1(data.collision)["value"].items():
        row, column = table1_slot(str(label))
        assert np.isclose(number(t1.loc[row, column]), number(value), rtol=1e-9) or (
            np.isnan(number(value)) and np.isnan(number(t1.loc[row, column]))), label
    t3 = pd.read_csv(paths.tables["table3_retargeting"]["csv"]).set_index("Method")
    assert t3.loc["IK only", "Wrist pos. mean (mm)"] == 20.0
    assert t3.loc["IK only", "Vel. viol."] == 1 and t3.loc["IK only", "Self-coll. frames"] == 2
    assert np.isnan(t3.loc["IK only", "Wrist pos. p95 (mm)"])  # only the critic measures it
    summary = json.loads(paths.summary.read_text())
    assert summary["collision.improved_pct"] == 50.0  # s1 improved, s2 got worse, s0 no collision
    assert summary["collision.reduction_median_pct"] == number(
        table1(data.collision).loc["Reduction (median, %)", "value"])
    assert summary["retarget.self_collision_frames"] == 2
    assert summary["sequences.failed"] == 1
    assert "retarget.refined.wrist_pos_mean_mm" not in summary  # no critic ran
    seqs = pd.read_csv(paths.sequences, keep_default_na=False).set_index("id")
    assert seqs.loc["s3", "error"] == "collide: boom" and seqs.loc["s1", "collide.improved"]
    html = paths.index.read_text()
    assert html.count('<table class="report"') == 4  # three tables + the summary
    assert "s3: collide: boom" in html
    assert summary["verdicts.processed_ok"] == 3 and summary["verdicts.export_valid"] == 1
    assert summary["verdicts.critic_accepted"] is None and summary["verdicts.total"] == 4
    assert seqs["export_valid"].to_dict() == {"s0": True, "s1": False, "s2": False,
                                              "s3": False}
    assert 'id="sequences"' in html and "Metric definitions" in html


def test_table2_only_with_ablation(tmp_path) -> None:
    data = _data()
    data.ablation = {"Collision only": data.collision, "+ Closeness": data.collision}
    paths = write_report(data, tmp_path / "r")
    assert "table2_ablation" in paths.tables
    t2 = pd.read_csv(paths.tables["table2_ablation"]["csv"])
    assert t2["Setting"].tolist() == ["Collision only", "+ Closeness"]
    # A later report without the ablation drops the stale Table II files.
    data.ablation = {}
    paths = write_report(data, tmp_path / "r")
    assert not (tmp_path / "r" / "table2_ablation.csv").exists()


def test_csvs_carry_no_float_noise(tmp_path) -> None:
    import re

    from embody.report.tables import Table

    data = _data()
    data.retarget.loc["s0", "wrist_pos_err_mm"] = 0.1 + 0.2  # 0.30000000000000004
    paths = write_report(data, tmp_path / "r")
    for csv in [paths.sequences, *(f["csv"] for f in paths.tables.values())]:
        for number in re.findall(r"\d+\.\d+", csv.read_text()):
            significant = number.replace(".", "").lstrip("0")
            assert len(significant) <= 10, (csv.name, number)
    assert "0.3," in paths.sequences.read_text()
    t = Table("t", "t", pd.DataFrame({"a": ["x"], "b": [1 / 3]}))
    assert t.to_csv() == "a,b\nx,0.3333333333\n"
