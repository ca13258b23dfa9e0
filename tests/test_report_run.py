"""A small real run (Prefect flow, critic on, one failing sequence) reported and exported.

The tables must hold exactly what the stages' own metric functions give on the stored
artifacts; the page must load in Chromium with every image; export/play must round-trip.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from embody.cli import main
from embody.config import load_config

ROBOT = "unitree_g1_dex3"
RUN = "tiny"
CHEAP = ["collision.steps=3", "collision.vertex_stride=8", "ik.iterations=3",
         "ik.shape_iterations=10", "critic.rounds=1", "render.preview_format=gif",
         "render.preview_max_frames=2",
         "render.width=64", "render.height=48", "render.keyframes=2", "run.workers=1",
         "run.critic=true", 'debug.fail_on=["seq2"]']


def _dataset(root: Path, frames: int = 8) -> Path:
    """Three AMASS-style sequences whose forearms cross into the chest (they collide)."""
    root.mkdir(parents=True)
    for k in range(3):
        poses = np.zeros((frames, 165))
        amp = 1.4 + 0.6 * np.sin(np.linspace(0, np.pi, frames) + 0.5 * k)[:, None]
        for j, v in ((16, [0, -0.6, -0.3]), (17, [0, 0.6, 0.3]), (18, [0, -1.2, 0]),
                     (19, [0, 1.2, 0])):
            poses[:, 3 * j:3 * j + 3] = amp * np.array(v)
        np.savez(root / f"seq{k}.npz", poses=poses, trans=np.zeros((frames, 3)),
                 betas=np.zeros(10), gender="neutral", mocap_frame_rate=30.0)
    index = root / "index.csv"
    index.write_text("path,text\n" + "".join(f"seq{k}.npz,sign {k} & more_50%\n" for k in range(3)))
    return index


def _flow(dataset: Path, store: Path, name: str, sets: list[str], pipeline=None) -> dict:
    from embody.flows.dataset import run_flow

    cfg = load_config(sets=[*CHEAP, *sets, f"run.store={store}", f"run.name={name}"])
    return run_flow(dataset, cfg, pipeline=pipeline)


@pytest.fixture(scope="module")
def run(tmp_path_factory, prefect_harness):
    """The store after one flow run; the flow itself wrote reports/<run> under `cwd`."""
    tmp = tmp_path_factory.mktemp("report_run")
    dataset = _dataset(tmp / "data")
    cwd = os.getcwd()
    os.chdir(tmp)
    try:
        summary = _flow(dataset, tmp / "store", RUN, [])
    finally:
        os.chdir(cwd)
    assert summary["failed"] == 1 and summary["report_error"] is None, summary
    return {"tmp": tmp, "store": tmp / "store", "dataset": dataset,
            "report": tmp / "reports" / RUN, "summary": summary}


def _library_results(store: Path):
    """The stage results of every ok sequence, read straight from the artifacts."""
    from embody.store import ArtifactStore, Manifest
    from embody.tasks.stages import COLLIDE, REFINE

    st = ArtifactStore(store)
    manifest = Manifest.load(st, RUN)
    coll, refined = {}, []
    for sid, seq in sorted(manifest.sequences.items()):
        if "collide" in seq["steps"]:
            art = st.read("collide", seq["steps"]["collide"])
            coll[sid] = COLLIDE.load(art.arrays, art.attrs).metrics
        if seq["status"] == "ok":
            art = st.read("refine", seq["steps"]["refine"])
            refined.append(REFINE.load(art.arrays, art.attrs))
    return pd.DataFrame.from_dict(coll, orient="index"), refined


def _close(a, b) -> bool:
    if a is None or (isinstance(a, float) and math.isnan(a)):
        return b is None or (isinstance(b, float) and math.isnan(b))
    return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)


def test_tables_equal_library_metric_functions(run) -> None:
    from embody.collision.metrics import table1
    from embody.critic import refine_table
    from embody.report.assemble import PAPER_TABLE1, number, table1_slot

    coll, refined = _library_results(run["store"])
    assert len(coll) == 2 and len(refined) == 2

    t1 = pd.read_csv(run["report"] / "table1_collision.csv").set_index("Metric")
    for label, value in table1(coll)["value"].items():
        row, column = table1_slot(label)
        cell = t1.loc[row, column]
        assert (cell == value) if isinstance(value, str) else _close(cell, value), label
    for row, paper in PAPER_TABLE1.items():
        assert t1.loc[row, "Paper (reported)"] == paper
    # The optimiser is judged by mesh penetration depth (it stops once no frame penetrates, so
    # the energy may stay where it was); neither measure may get worse.
    energy = t1.loc["Collision energy (mean)"]
    assert float(energy["Before"]) >= float(energy["After"])
    depth = t1.loc["Max depth mm"]
    assert float(depth["After"]) <= float(depth["Before"])

    assert not (run["report"] / "table2_ablation.csv").exists()  # only with --ablation

    t3 = pd.read_csv(run["report"] / "table3_retargeting.csv").set_index("Method")
    lib3 = refine_table(refined)
    # location-preserving targets (the default): the retarget step's row is "Location-preserving"
    for method, label in (("Location-preserving", "IK-only"), ("Refined (geometric)", "refined")):
        for header, key, scale in (("Wrist pos. mean (mm)", "wrist_mm_mean", 1),
                                   ("Wrist pos. p95 (mm)", "wrist_mm_p95", 1),
                                   ("Wrist rot. mean (deg)", "wrist_deg_mean", 1),
                                   ("DTW wrist (mm)", "wrist_dtw_mm", 1),
                                   ("Rounds", "rounds", 1), ("Accepted (%)", "accepted", 100)):
            assert _close(t3.loc[method, header], lib3.loc[label, key] * scale), (method, header)
        assert t3.loc[method, "N"] == 2
        assert t3.loc[method, "Limit viol."] == 0  # the IK clips to the limits
    # the plain shape-fit IK (solved by the metrics step) and the fidelity columns of every row
    assert t3.loc["IK only", "N"] == 2 and t3.loc["IK only", "Limit viol."] == 0
    for method in ("IK only", "Location-preserving", "Refined (geometric)"):
        assert t3.loc[method, "Location err. (scale)"] >= 0 and 0 <= t3.loc[method, "Palm orient. (deg)"] <= 180
    seqs = pd.read_csv(run["report"] / "sequences.csv").set_index("id")
    assert seqs.loc["seq0", "metrics.fidelity.refined.location_err"] >= 0

    summary = json.loads((run["report"] / "summary.json").read_text())
    assert summary["sequences.ok"] == 2 and summary["sequences.failed"] == 1
    assert _close(summary["collision.reduction_median_pct"], coll["reduction_pct"].median())
    assert _close(summary["collision.improved_pct"],
                  number(table1(coll).loc["Improved n/N (%)", "value"]))
    assert _close(summary["retarget.refined.wrist_pos_mean_mm"], lib3.loc["refined", "wrist_mm_mean"])
    assert _close(summary["retarget.preserving.wrist_pos_mean_mm"], lib3.loc["IK-only", "wrist_mm_mean"])
    # The three verdicts: the report, summary.json and the run's own summary agree.
    verdicts = {k.split(".", 1)[1]: v for k, v in summary.items() if k.startswith("verdicts.")}
    assert verdicts == run["summary"]["verdicts"]
    manifest_seqs = json.loads((run["store"] / "runs" / RUN / "manifest.json").read_text())
    from embody.verdicts import sequence_verdicts
    assert run["summary"]["sequences"] == {
        sid: sequence_verdicts(seq) for sid, seq in manifest_seqs["sequences"].items()}
    assert verdicts["processed_ok"] == 2 and verdicts["total"] == 3
    assert verdicts["critic_accepted"] == int(lib3.loc["refined", "accepted"] * 2 + 0.5)
    t0 = pd.read_csv(run["report"] / "verdicts.csv", keep_default_na=False).set_index("Verdict")
    assert t0.loc["Export-valid", "Sequences"] == f"{verdicts['export_valid']}/3"
    # the fourth verdict: the physics step ran on both finished sequences
    assert verdicts["physics_valid"] is not None and 0 <= verdicts["physics_valid"] <= 2
    assert t0.loc["Physics-valid", "Sequences"] == f"{verdicts['physics_valid']}/3"
    assert summary["physics.valid_pct"] == pytest.approx(50.0 * verdicts["physics_valid"])
    for key in ("collision.pose_mse_median", "collision.daccel_mse_median",
                "collision.runtime_mean_s", "retarget.refined.wrist_rot_mean_deg",
                "retarget.limit_violations", "retarget.self_collision_frames"):
        assert summary[key] is not None, key


def test_report_files_and_page(run) -> None:
    report = run["report"]
    for name in ("verdicts", "table1_collision", "table3_retargeting", "table3_physics"):
        for ext in ("csv", "md", "tex"):
            assert (report / f"{name}.{ext}").stat().st_size > 0
        tex = (report / f"{name}.tex").read_text()
        assert r"\toprule" in tex and r"\bottomrule" in tex
    seqs = pd.read_csv(report / "sequences.csv", keep_default_na=False).set_index("id")
    assert seqs["status"].to_dict() == {"seq0": "ok", "seq1": "ok", "seq2": "failed"}
    assert "InjectedFailure" in seqs.loc["seq2", "error"]
    assert seqs.loc["seq0", "text"] == "sign 0 & more_50%"
    assert {"collide.reduction_pct", "retarget.wrist_pos_err_mm", "refine.wrist_mm_mean",
            "refine.accepted", "validation.self_collision_frames", "metrics.mean_jerk",
            "source.frames", "processed_ok", "export_valid", "critic_accepted"} <= set(seqs.columns)
    assert not seqs.loc["seq2", "processed_ok"] and seqs.loc["seq0", "processed_ok"]
    figures = {p.relative_to(report).as_posix() for p in (report / "figures").rglob("*.png")}
    assert {"figures/collision_energy.png", "figures/pose_vs_reduction.png",
            "figures/wrists/seq0.png", "figures/wrists/seq1.png",
            "figures/sheets/seq0.png", "figures/location/seq0.png",
            "figures/location/seq1.png"} <= figures
    html = (report / "index.html").read_text()
    assert all(f in html for f in figures)
    previews = sorted(p.name for p in (report / "figures" / "previews").iterdir())
    assert previews == ["seq0.gif", "seq1.gif"]  # the render stage's, linked from the page
    assert all(f"figures/previews/{p}" in html for p in previews)
    from conftest import CHROMIUM_INSTALL, require_tool
    from test_report_html import check_report_page
    require_tool(("chromium", "chromium-browser"), CHROMIUM_INSTALL)
    attrs = check_report_page(report / "index.html", run["tmp"],
                              {"verdicts", "table1_collision", "table3_retargeting", "table3_physics",
                               "sequences"})
    links = {r["id"]: r["links"] for r in attrs["rows"]}
    # sheet, preview, wrist, location and physics plots; none for the failed sequence
    assert {len(links["seq0"]), len(links["seq1"]), len(links["seq2"])} == {5, 0}


def test_tex_tables_compile(run, pdflatex, tmp_path) -> None:
    for name in ("verdicts", "table1_collision", "table3_retargeting", "table3_physics"):
        shutil.copy(run["report"] / f"{name}.tex", tmp_path)
    (tmp_path / "doc.tex").write_text(
        "\\documentclass{article}\\usepackage{booktabs}\\begin{document}"
        "\\input{verdicts.tex}\\input{table1_collision.tex}\\input{table3_retargeting.tex}"
        "\\input{table3_physics.tex}\\end{document}\n")
    proc = subprocess.run([pdflatex, "-interaction=nonstopmode", "-halt-on-error", "doc.tex"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:]


def test_report_cli_is_deterministic(run, tmp_path) -> None:
    out = tmp_path / "again"
    assert main(["report", RUN, "--store", str(run["store"]), "--out", str(out), "--json"]) == 0
    for path in sorted(run["report"].rglob("*")):
        if path.is_file():
            rel = path.relative_to(run["report"])
            assert (out / rel).read_bytes() == path.read_bytes(), rel
    assert main(["report", "nope", "--store", str(run["store"])]) == 2


def test_ablation_reuses_cache(run, tmp_path) -> None:
    """Table II's settings all run in the ablation store (same flow, same timing for every
    row), leave the main store alone, and are cached there for the next `--ablation`."""
    from embody.collision.metrics import table2
    from embody.report.reader import latest_run, metrics_frame, open_run
    from embody.store import ArtifactStore

    st = ArtifactStore(run["store"])
    abl = ArtifactStore(run["store"] / "ablation")
    before = {s: len(st.computations(s)) for s in ("source", "collide", "retarget", "refine")}
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        for _ in range(2):
            assert main(["report", RUN, "--store", str(run["store"]), "--out",
                         str(tmp_path / "r"), "--ablation"]) == 0
    finally:
        os.chdir(cwd)
    assert {s: len(st.computations(s)) for s in before} == before
    # 3 settings × the 2 sequences that collide (seq2's injected failure is in collide);
    # the second --ablation computes nothing.
    assert len(abl.computations("collide")) == 6
    assert not (tmp_path / "reports").exists()  # the internal runs write no reports
    t2 = pd.read_csv(tmp_path / "r" / "table2_ablation.csv").set_index("Setting")
    assert t2.index.tolist() == ["Collision only", "+ Closeness", "+ Closeness + Smoothness"]
    settings = {s: metrics_frame(open_run(abl.root, f"{RUN}.ablation-{slug}")[1], "collide")
                for s, slug in (("Collision only", "collision-only"), ("+ Closeness", "closeness"),
                                ("+ Closeness + Smoothness", "closeness-smoothness"))}
    lib = table2(settings)
    for setting in lib.index:
        for column in lib.columns:
            assert _close(t2.loc[setting, column], lib.loc[setting, column]), (setting, column)
    # An internal ablation run is never "the latest run" `embody report` picks.
    (st.runs_dir / f"{RUN}.ablation-x").mkdir(exist_ok=True)
    (st.runs_dir / f"{RUN}.ablation-x" / "manifest.json").write_text("{}")
    assert latest_run(run["store"]) == RUN


@pytest.mark.parametrize("fmt", ["npz", "csv"])
def test_export_library(run, tmp_path, fmt) -> None:
    from embody.export.runs import run_trajectories
    from embody.export.library import VIOLATION_KEYS, Trajectory

    from embody.verdicts import export_valid

    # Default: sequences the critic rejected are left out, named as such; the default export
    # writes exactly what the run's verdicts say it writes.
    out = tmp_path / "lib"
    assert main(["export", RUN, str(out), "--robot", ROBOT, "--store", str(run["store"]),
                 "--format", fmt]) == 1
    excluded = pd.read_csv(out / "excluded.csv").set_index("id")
    summary = json.loads((run["report"] / "summary.json").read_text())
    written = pd.read_csv(out / "library.csv") if (out / "library.csv").stat().st_size else []
    assert len(written) == run["summary"]["verdicts"]["default_export"] == summary["verdicts.default_export"]
    rejected = {i for i in excluded.index if "critic rejected" in excluded.loc[i, "reason"]}
    assert len(rejected) == 2 - summary["verdicts.critic_accepted"]
    # --include-rejected: exactly the export-valid sequences of the run summary are exported.
    code = main(["export", RUN, str(out), "--robot", ROBOT, "--store", str(run["store"]),
                 "--format", fmt, "--include-rejected"])
    assert code == 1  # seq2 failed in the run, so it is excluded
    exported = set(pd.read_csv(out / "library.csv")["id"]) if (out / "library.csv").stat().st_size else set()
    assert exported == {i for i, v in run["summary"]["sequences"].items() if v["export_valid"]}
    assert all(export_valid(t.validation) == (t.id in exported)
               for t in run_trajectories(run["store"], RUN, ROBOT)[0])
    library = pd.read_csv(out / "library.csv")
    excluded = pd.read_csv(out / "excluded.csv").set_index("id")
    assert excluded.loc["seq2", "status"] == "failed"
    assert set(library["id"]) | set(excluded.index) == {"seq0", "seq1", "seq2"}
    trajectories, _ = run_trajectories(run["store"], RUN, ROBOT)
    for traj in trajectories:
        bad = any(traj.validation[k] for k in VIOLATION_KEYS)
        assert (traj.id in set(excluded.index)) == bad
        if bad:
            assert excluded.loc[traj.id, "status"] == "excluded"
            continue
        path = out / f"{traj.id}.{fmt}"
        if fmt == "npz":
            back = Trajectory.load(path)
            np.testing.assert_array_equal(back.q, traj.q)
            assert back.dt == 0.02 and back.text == f"sign {traj.id[-1]} & more_50%"
            assert back.validation["refined"] is True
        else:
            table = pd.read_csv(path)
            assert table.columns[0] == "time" and list(table.columns[1:]) == list(traj.joint_names)
            np.testing.assert_allclose(table.iloc[:, 1:].to_numpy(), traj.q, atol=1e-8)
    assert main(["export", RUN, str(out), "--robot", "unitree_h1", "--store",
                 str(run["store"])]) == 2


def test_export_on_a_full_disk_is_one_line_and_leaves_no_file(run, tmp_path, monkeypatch,
                                                              capsys) -> None:
    """The disk under OUT fills after 2 KB (os.write is the OS's write: an outside fault): one
    line, exit 1, and OUT holds nothing of the export (no truncated file, no index)."""
    import errno

    out = tmp_path / "lib"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    real_write = os.write
    left = [2000]

    def write(fd: int, data) -> int:
        if not os.readlink(f"/proc/self/fd/{fd}").startswith(str(out)):
            return real_write(fd, data)
        n = min(len(data), left[0])
        if n == 0 and len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        left[0] -= n
        return real_write(fd, bytes(data[:n]))

    monkeypatch.setattr(os, "write", write)
    capsys.readouterr()
    code = main(["export", RUN, str(out), "--robot", ROBOT, "--store", str(run["store"]),
                 "--format", "csv", "--include-rejected"])
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert "no space left on device" in err and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]


def test_export_refuses_tampered_store(run, tmp_path) -> None:
    """A stored control-rate array edited to penetrate (its stored counters still 0) is refused:
    the export validates the file it writes, not the counters it was handed."""
    import zarr

    from embody.export.runs import run_trajectories
    from embody.store import ArtifactStore, Manifest

    store = tmp_path / "store"
    shutil.copytree(run["store"], store)
    st = ArtifactStore(store)
    manifest = Manifest.load(st, RUN)
    ok = [sid for sid, seq in sorted(manifest.sequences.items()) if seq["status"] == "ok"]
    exported = {t.id for t in run_trajectories(store, RUN, ROBOT)[0]
                if not any(t.validation[k] for k in ("joint_limit_violations", "velocity_violations",
                                                     "self_collision_frames"))}
    sid = sorted(exported)[0]
    group = zarr.open_group(str(st.path("metrics", manifest.sequences[sid]["steps"]["metrics"])),
                            mode="r+")
    from embody.robot import load_robot
    robot = load_robot()
    q = robot.rest.copy()
    for name, v in (("left_shoulder_pitch_joint", -0.6), ("right_shoulder_pitch_joint", -0.6),
                    ("left_elbow_joint", 1.0), ("right_elbow_joint", 1.0),
                    ("left_shoulder_yaw_joint", -0.5), ("right_shoulder_yaw_joint", 0.5)):
        q[robot.joint_index(name)] = v  # the hands inside each other
    arr = group["q_control"]
    arr[:] = np.tile(q, (arr.shape[0], 1))
    # Re-record its digests and checksum too, as a buggy writer would have: the store's own
    # integrity check then passes, so only the export's re-validation can catch it.
    from embody.store.artifacts import array_digest, arrays_checksum
    attrs = dict(group.attrs)
    root = st.path("metrics", manifest.sequences[sid]["steps"]["metrics"])
    arrays = {name: np.asarray(a[...]) for name, a in group.arrays()}
    attrs["embody"] = {**attrs["embody"], "checksum": arrays_checksum(arrays),
                       "digests": {n: array_digest(a) for n, a in arrays.items()},
                       "files": {f.relative_to(root).as_posix(): f.stat().st_size
                                 for f in sorted(root.rglob("*"))
                                 if f.is_file() and f.name != "zarr.json"}}
    group.attrs.update(attrs)
    out = tmp_path / "lib"
    # --include-rejected: the tampered sequence must reach the file check even if the critic
    # rejected it (rejected sequences are excluded before any file is written).
    assert main(["export", RUN, str(out), "--robot", ROBOT, "--store", str(store),
                 "--include-rejected"]) == 1
    excluded = pd.read_csv(out / "excluded.csv").set_index("id")
    # refused at the file check, or (a sequence whose stored torque counter is not 0) before it
    status, reason = excluded.loc[sid, "status"], excluded.loc[sid, "reason"]
    assert (status, "self_collision_frames" in reason) == ("refused", True) or (
        status == "excluded" and "torque_viol" in reason)
    assert sid not in set(pd.read_csv(out / "library.csv")["id"]) and len(ok) >= 1
    assert not (out / f"{sid}.npz").exists()


def test_play_writes_preview(run, tmp_path) -> None:
    from embody.export.runs import run_trajectories

    traj = run_trajectories(run["store"], RUN, ROBOT)[0][0]
    npz = traj.save_npz(tmp_path / "t.npz")
    code = main(["play", str(npz), "--out", str(tmp_path / "prev"), "--format", "gif",
                 "--set", "render.width=64", "--set", "render.height=48",
                 "--set", "render.preview_max_frames=3"])
    assert code == 0
    from PIL import Image
    with Image.open(tmp_path / "prev.gif") as im:
        assert im.size == (64, 48) and im.n_frames >= 2  # GIF merges identical frames
        assert (np.asarray(im.convert("RGB")).sum(-1) > 30).mean() > 0.01  # the robot shows
    (tmp_path / "bad.npz").write_bytes(b"nope")
    assert main(["play", str(tmp_path / "bad.npz")]) == 2


def test_readme_tables_script(run, tmp_path) -> None:
    script = Path(__file__).resolve().parents[1] / "scripts" / "readme_tables.py"
    readme = tmp_path / "README.md"
    readme.write_text("intro\n<!-- tables:start -->\nold\n<!-- tables:end -->\noutro\n")
    proc = subprocess.run([sys.executable, str(script), str(run["report"]), "--write",
                           str(readme)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    text = readme.read_text()
    assert text.startswith("intro\n<!-- tables:start -->") and text.endswith("<!-- tables:end -->\noutro\n")
    assert "old" not in text
    for name in ("verdicts", "table1_collision", "table3_retargeting", "table3_physics"):
        assert (run["report"] / f"{name}.md").read_text().strip() in text
    assert "**Table II:" not in text  # no ablation run, no Table II
    assert "- **Collision energy**:" in text


def test_fully_cached_rerun_skips_prefect(run, tmp_path, capsys) -> None:
    """When the store holds every result, `embody run` records the run (manifest, table,
    report) without starting Prefect; an unchanged rerun keeps the report as it is."""
    from embody.flows.warm import run_cached

    sets = [x for s in CHEAP if not s.startswith("debug.") for x in ("--set", s)]
    args = ["run", str(run["dataset"]), "--store", str(run["store"]), "--name", "warm",
            "--limit", "2", "--json", *sets]  # seq0, seq1: every step is stored by `run`
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert main(args) == 0
        first = capsys.readouterr()
        summary = json.loads(first.out)
        index = tmp_path / "reports" / "warm" / "index.html"
        stamp = index.stat().st_mtime_ns
        assert main(args) == 0
        second = json.loads(capsys.readouterr().out)
    finally:
        os.chdir(cwd)
    assert first.err.startswith("embody run: starting")  # says what is starting, first
    assert summary["prefect"] is False and second["prefect"] is False
    assert set(summary["computed"].values()) == {0} and summary["ok"] == 2
    assert summary["verdicts"]["total"] == 2
    assert summary["sequences"] == {k: v for k, v in run["summary"]["sequences"].items()
                                    if k in ("seq0", "seq1")}
    tiny = json.loads((run["store"] / "runs" / RUN / "manifest.json").read_text())
    warm = json.loads((run["store"] / "runs" / "warm" / "manifest.json").read_text())
    for sid in ("seq0", "seq1"):
        assert warm["sequences"][sid]["steps"] == tiny["sequences"][sid]["steps"]
        assert warm["sequences"][sid]["status"] == "ok"
    assert warm["finished"] is not None
    assert index.stat().st_mtime_ns == stamp  # same manifest content: report kept
    assert (run["store"] / "runs" / "warm" / "sequences.csv").is_file()
    # Anything missing (here: another collision setting) → the flow has to run.
    cfg = load_config(sets=[*CHEAP[:-1], "collision.steps=4", f"run.store={run['store']}",
                            "run.name=cold"])
    assert run_cached(run["dataset"], cfg) is None
    assert not (run["store"] / "runs" / "cold").exists()
