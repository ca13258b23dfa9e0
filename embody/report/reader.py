"""Read one run from the artifact store into `RunData` (manifest + the artifacts it names).

Metric dicts come from the manifest (what each step's library call returned). Table III's
validation counters are those the metrics step stored for the exported control-rate array
(computed here with the same functions only for runs that predate them); the wrist figures
need the robot and use the retargeting stage's own functions on the stored trajectories.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from embody.errors import InputError
from embody.report.data import RunData

log = logging.getLogger(__name__)

#: Step names as the orchestrator stores them (tasks/stages.py).
SOURCE, COLLIDE, SHAPE_FIT = "source", "collide", "shape_fit"
RETARGET, REFINE, RENDER, METRICS = "retarget", "refine", "render", "metrics"


def open_run(store_root: str | Path, run: str) -> tuple[Any, Any]:
    """(ArtifactStore, Manifest) of `run`; InputError naming the known runs when it is absent."""
    from embody.store.artifacts import ArtifactStore
    from embody.store.manifest import Manifest, check_run_name

    store = ArtifactStore(store_root)
    path = store.runs_dir / check_run_name(run, "RUN") / "manifest.json"
    if not path.is_file():
        runs = sorted(p.parent.name for p in store.runs_dir.glob("*/manifest.json"))
        known = ", ".join(runs) or "none"
        raise InputError(path, None, f"no run {run!r} in the store (runs: {known})")
    return store, Manifest.load(store, run)


def run_config(manifest: Any) -> Any:
    """The config the run used (recorded in its manifest)."""
    from pydantic import ValidationError

    from embody.config import Config

    try:
        return Config.model_validate(manifest.data.get("config") or {})
    except ValidationError as exc:
        raise InputError(manifest.path, "config", "the recorded config does not validate with "
                         f"this version (rerun `embody run`): {exc.errors()[0]['msg']}") from None


#: Run names of `embody report --ablation`'s Table II settings (`<run>.ablation-<setting>`).
ABLATION_MARK = ".ablation-"


def is_main_run(name: str) -> bool:
    """False for the internal runs of `report --ablation` (older stores keep them beside the
    main runs); `embody report` with no name never picks those."""
    return ABLATION_MARK not in name


def latest_run(store_root: str | Path) -> str:
    """The most recently written main run of a store (what `embody report` shows by default)."""
    runs = sorted((p for p in Path(store_root, "runs").glob("*/manifest.json")
                   if is_main_run(p.parent.name)), key=lambda p: p.stat().st_mtime)
    if not runs:
        raise InputError(Path(store_root), None, "the store has no runs (run `embody run` first)")
    return runs[-1].parent.name


def metrics_frame(manifest: Any, step: str) -> pd.DataFrame:
    """One row per sequence that has `step`'s metrics, indexed by sequence id."""
    rows = {sid: seq["metrics"][step] for sid, seq in sorted(manifest.sequences.items())
            if step in seq.get("steps", {}) and step in seq.get("metrics", {})}
    frame = pd.DataFrame.from_dict(rows, orient="index")
    frame.index.name = "id"
    return frame


def exported_trajectory(store: Any, robot: Any, seq: dict[str, Any], ik: Any,
                        q: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """The control-rate array `embody export` writes for a sequence and its validation counters:
    both as the metrics step stored them; for runs made before it stored them, built now with
    the same function (`retarget.control.control_trajectory`) and validated here."""
    from embody.retarget.control import control_trajectory
    from embody.retarget.validation import VALIDATION_KEYS, validation_counts

    stored = seq.get("metrics", {}).get(METRICS, {})
    if METRICS in seq.get("steps", {}) and "validation_rate_hz" in stored:
        art = store.read(METRICS, seq["steps"][METRICS])
        if "q_control" in art.arrays:
            return (np.asarray(art.arrays["q_control"]),
                    {k: float(stored[k]) for k in VALIDATION_KEYS})
    q_control = control_trajectory(robot, q, ik.fps, ik.control_rate_hz)
    return q_control, validation_counts(robot, q_control, ik.control_rate_hz)


def final_validation(store: Any, robot: Any, seq: dict[str, Any], ik: Any,
                     q: np.ndarray) -> dict[str, float]:
    """Validation counters of the exported array of a sequence's final trajectory q."""
    from embody.retarget.validation import VALIDATION_KEYS

    stored = seq.get("metrics", {}).get(METRICS, {})
    if "validation_rate_hz" in stored and all(k in stored for k in VALIDATION_KEYS):
        return {k: float(stored[k]) for k in VALIDATION_KEYS}
    return exported_trajectory(store, robot, seq, ik, q)[1]


def load_result(store: Any, seq: dict[str, Any], step: str) -> Any:
    """The stored result of `step` for one manifest sequence entry, as the stage's own type."""
    from embody.tasks.stages import COLLIDE as C, REFINE as R, RENDER as V, RETARGET as T, SOURCE as S

    loader = {s.name: s.load for s in (S, C, T, R, V)}[step]
    art = store.read(step, seq["steps"][step])
    return loader(art.arrays, art.attrs)


class _Robotics:
    """The run's robot (and body, shape fit) loaded on first use."""

    def __init__(self, store: Any, manifest: Any) -> None:
        self.store, self.manifest, self.cfg = store, manifest, run_config(manifest)
        self._robot = self._body = self._fit = None

    @property
    def robot(self) -> Any:
        if self._robot is None:
            from embody.robot import load_robot
            self._robot = load_robot(self.cfg.robot)
        return self._robot

    def _body_fit(self) -> tuple[Any, Any]:
        from embody.body import load_body_model
        from embody.retarget import ShapeFit

        if self._fit is None:
            art = self.store.read(SHAPE_FIT, self.manifest.data["shared"][SHAPE_FIT])
            self._fit = ShapeFit.from_arrays(art.arrays, art.attrs)
            self._body = load_body_model(self.cfg.body)
        return self._body, self._fit

    def reference_wrists(self, motion: Any) -> np.ndarray:
        """The IK's reference wrist positions (T,2,3), rebuilt as the retarget step did."""
        from embody.retarget import build_targets

        body, fit = self._body_fit()
        return np.asarray(build_targets(motion, body, fit, self.robot, self.cfg.ik).wrist_pos)

    def sheet(self, motion: Any, result: Any, title: str) -> bytes:
        """The critic's final comparison sheet (human over robot at its keyframes), re-rendered
        with the render stage's own functions: the refine step keeps hashes, not images."""
        from embody.render.compare import open_renderer, reference_vertices, render_comparison

        body, fit = self._body_fit()
        keys = np.asarray(result.keyframes)
        renderer = open_renderer(self.robot, body, fit, self.cfg.render)
        try:
            comp = render_comparison(renderer, self.cfg.render, keys, motion.fps, result.final.q,
                                     reference_verts=reference_vertices(motion, body, fit, keys))
            return comp.sheet_png(title)
        finally:
            renderer.close()

    def wrists(self, q: np.ndarray) -> np.ndarray:
        from embody.critic.refine import robot_wrists
        return robot_wrists(self.robot, q)[0]


def collect(store_root: str | Path, run: str, *, max_figures: int = 24,
            max_sheets: int = 4) -> RunData:
    """Everything a report needs about `run`.

    Every sequence the render stage rendered gets its stored comparison sheet and preview (a
    copy, no rendering). Wrist plots (robot FK plus a plot, ~0.5 s each) are drawn for the
    `max_figures` sequences with the largest IK wrist error; sequences without a stored render
    get a re-rendered sheet for the first `max_sheets` of those (~2 s each). So a
    20k-sequence run still gets a page in bounded time, and the page states the rule.
    """
    from embody.render import RenderError
    from embody.retarget.validation import validation_counts

    store, manifest = open_run(store_root, run)
    seqs = manifest.sequences
    ids = sorted(seqs)
    sequences = pd.DataFrame(
        {"status": [seqs[i]["status"] for i in ids],
         "failed_step": [seqs[i].get("failed_step") or "" for i in ids],
         "error": [seqs[i].get("error") or "" for i in ids],
         "text": [_text(store, seqs[i]) for i in ids]},
        index=pd.Index(ids, name="id"))
    data = RunData(name=run, sequences=sequences, collision=metrics_frame(manifest, COLLIDE),
                   retarget=metrics_frame(manifest, RETARGET))
    steps = {step for seq in seqs.values() for step in seq.get("metrics", {})}
    data.other = {step: metrics_frame(manifest, step) for step in sorted(steps)
                  if step not in (COLLIDE, RETARGET, REFINE)}
    ok = [i for i in ids if seqs[i]["status"] == "ok" and RETARGET in seqs[i]["steps"]]
    if not ok:
        return data
    robotics = _Robotics(store, manifest)
    critic = robotics.cfg.critic.kind
    ik = {i: load_result(store, seqs[i], RETARGET) for i in ok}
    refined = {i: load_result(store, seqs[i], REFINE) for i in ok if REFINE in seqs[i]["steps"]}
    if "self_collision_frames" not in data.retarget:
        extra = {i: validation_counts(robotics.robot, ik[i].q, ik[i].fps) for i in ok}
        data.retarget["self_collision_frames"] = pd.Series(
            {i: v["self_collision_frames"] for i, v in extra.items()})
    if not refined:  # the IK trajectory is the final one: its validity is the exported array's
        exported = pd.DataFrame.from_dict(
            {i: final_validation(store, robotics.robot, seqs[i], ik[i], ik[i].q) for i in ok},
            orient="index")
        for key in exported:
            data.retarget.loc[ok, key] = exported[key]
    if refined:
        data.refine[critic] = [refined[i] for i in sorted(refined)]
        data.refined[critic] = metrics_frame(manifest, REFINE)
        data.validation[critic] = pd.DataFrame.from_dict(
            {i: final_validation(store, robotics.robot, seqs[i], ik[i], r.q)
             for i, r in refined.items()},
            orient="index")
    for sid in ok:  # the render stage stored it: no re-rendering
        if RENDER in seqs[sid]["steps"]:
            stored = load_result(store, seqs[sid], RENDER)
            data.sheets[sid] = stored.sheet_png
            if stored.preview is not None:
                data.previews[sid] = (stored.preview, stored.preview_suffix or ".bin")
    worst = data.retarget.loc[ok, "wrist_pos_err_mm"].sort_values(ascending=False, kind="stable")
    chosen = list(worst.index[:max_figures])
    if len(chosen) < len(ok):
        data.figure_rule = (f"Wrist plots: the {len(chosen)} of {len(ok)} finished sequences "
                            "with the largest IK-only wrist position error (`embody report "
                            "--max-figures N` draws more).")
    for rank, sid in enumerate(chosen):
        if sid in refined:
            r = refined[sid]
            tracks = {"reference": r.ik_only.target_pos, "IK only": robotics.wrists(r.ik_only.q),
                      "refined": robotics.wrists(r.final.q)}
            if sid not in data.sheets and rank < max_sheets:
                motion = load_result(store, seqs[sid], COLLIDE).motion
                try:
                    data.sheets[sid] = robotics.sheet(motion, r, f"{sid}: final round")
                except RenderError as exc:  # no offscreen GL here: the rest of the report stands
                    log.warning("comparison sheet of %s not rendered: %s", sid, exc)
                    max_sheets = 0
        else:
            motion = load_result(store, seqs[sid], COLLIDE).motion
            tracks = {"reference": robotics.reference_wrists(motion),
                      "IK only": robotics.wrists(ik[sid].q)}
        data.wrists[sid] = tracks
        data.wrist_fps[sid] = float(ik[sid].fps)
    missing = [i for i in ok if i not in data.sheets]
    if missing and any(RENDER not in seqs[i]["steps"] for i in missing):
        data.figure_rule += (" Comparison sheets: stored by the render stage for every rendered "
                             f"sequence; re-rendered for at most {max_sheets} of the others "
                             "(`--max-sheets`).")
    return data


def _text(store: Any, seq: dict[str, Any]) -> str:
    """The sign's text from the source motion's attrs (read without loading its arrays)."""
    key = seq.get("steps", {}).get(SOURCE)
    if key is None:
        return ""
    doc = json.loads((store.path(SOURCE, key) / "zarr.json").read_text())
    return str(doc.get("attributes", {}).get("result", {}).get("meta", {}).get("text", ""))


def run_robot(store_root: str | Path, run: str) -> Any:
    """The robot `run` was retargeted for, as its recorded config loads it."""
    from embody.robot import load_robot

    return load_robot(run_config(open_run(store_root, run)[1]).robot)


def run_trajectories(store_root: str | Path, run: str, robot_name: str
                     ) -> tuple[list[Any], list[tuple[str, str]]]:
    """The exported (control-rate) trajectory of every finished sequence of `run` (from the
    refined one when the critic ran) with its stored validation counters, and (id, reason) of
    the sequences the run itself failed."""
    from embody.report.library import Trajectory

    store, manifest = open_run(store_root, run)
    robotics = _Robotics(store, manifest)
    if robotics.cfg.robot.name != robot_name:
        raise InputError(manifest.path, "robot", f"run {run!r} was retargeted for "
                         f"{robotics.cfg.robot.name!r}, not {robot_name!r}")
    out, failed = [], []
    for sid, seq in sorted(manifest.sequences.items()):
        if seq["status"] != "ok" or RETARGET not in seq["steps"]:
            failed.append((sid, f"run {seq['status']}: {seq.get('error') or 'not retargeted'}"))
            continue
        ik = load_result(store, seq, RETARGET)
        if REFINE in seq["steps"]:
            final = load_result(store, seq, REFINE)
            q = np.asarray(final.q, dtype=np.float64)
            scores = {**final.final.metrics, "refined": True, "accepted": bool(final.accepted)}
        else:
            q = np.asarray(ik.q, dtype=np.float64)
            scores = {"wrist_mm_mean": ik.metrics.get("wrist_pos_err_mm"),
                      "wrist_deg_mean": ik.metrics.get("wrist_rot_err_deg"), "refined": False}
        q_control, counts = exported_trajectory(store, robotics.robot, seq, ik, q)
        validation = {**scores, **counts, "fps": ik.fps, "control_rate_hz": ik.control_rate_hz}
        out.append(Trajectory(id=sid, robot=robot_name, joint_names=tuple(ik.joint_names),
                              q=q_control, dt=1.0 / ik.control_rate_hz, text=_text(store, seq),
                              validation=validation))
    return out, failed
