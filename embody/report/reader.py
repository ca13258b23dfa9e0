"""Read one run from the artifact store into `RunData`: a pure reader.

Every number and image comes from what the pipeline stored: the manifest's per-step metric
dicts, the metrics step's arrays (wrist tracks, per-frame location error) and the render step's
comparison sheets and previews. Nothing is recomputed here, and nothing of the robot, the body,
the renderer, the critic or the stages is imported (a test checks the imports), so a report of a
20k-sequence run costs reading plus plotting. A run whose store lacks something the page shows
(an older run) gets a blank cell and a note, never a recomputed value.
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
PHYSICS = "physics"


def open_run(store_root: str | Path, run: str) -> tuple[Any, Any]:
    """(ArtifactStore, Manifest) of `run`; InputError naming the known runs when it is absent."""
    from embody.store.artifacts import ArtifactStore
    from embody.store.manifest import Manifest, check_run_name

    store = ArtifactStore(store_root)
    names = store.run_names()
    if check_run_name(run, "RUN") not in names:
        known = ", ".join(names) or "none"
        raise InputError(store.manifest_path(run), None,
                         f"no run {run!r} in the store (runs: {known})")
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
    from embody.store.artifacts import ArtifactStore

    store = ArtifactStore(store_root)
    runs = sorted((r for r in store.run_names() if is_main_run(r)), key=store.manifest_mtime)
    if not runs:
        raise InputError(Path(str(store_root)), None,
                         "the store has no runs (run `embody run` first)")
    return runs[-1]


def metrics_frame(manifest: Any, step: str) -> pd.DataFrame:
    """One row per sequence that has `step`'s metrics, indexed by sequence id."""
    rows = {sid: seq["metrics"][step] for sid, seq in sorted(manifest.sequences.items())
            if step in seq.get("steps", {}) and step in seq.get("metrics", {})}
    frame = pd.DataFrame.from_dict(rows, orient="index")
    frame.index.name = "id"
    return frame


#: Validation counters of the exported array (stored by the metrics step).
VALIDATION_KEYS = ("joint_limit_violations", "velocity_violations", "self_collision_frames", "torque_viol")
#: The metrics step's prefix for the critic's metrics of its IK-only round.
CRITIC_IK = "critic_ik."


def _prefixed(frame: pd.DataFrame, prefix: str) -> pd.DataFrame:
    cols = [c for c in frame.columns if str(c).startswith(prefix)]
    return frame[cols].rename(columns=lambda c: c[len(prefix):]).dropna(how="all")


def _metrics_arrays(store: Any, seq: dict[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The metrics step's arrays and labels of one sequence ({} when it has none)."""
    key = seq.get("steps", {}).get(METRICS)
    if key is None:
        return {}, {}
    art = store.read(METRICS, key)
    return art.arrays, dict(art.attrs.get("labels", {}))


def _render(store: Any, seq: dict[str, Any]) -> tuple[bytes | None, tuple[bytes, str] | None]:
    """The render step's comparison sheet (PNG bytes) and preview (bytes, suffix)."""
    key = seq.get("steps", {}).get(RENDER)
    if key is None:
        return None, None
    art = store.read(RENDER, key)
    sheet = np.asarray(art.arrays["sheet_png"]).tobytes() if "sheet_png" in art.arrays else None
    preview = art.arrays.get("preview")
    suffix = art.attrs.get("preview_suffix") or ".bin"
    return sheet, (None if preview is None else (np.asarray(preview).tobytes(), suffix))


def collect(store_root: str | Path, run: str, *, max_figures: int | None = 24,
            max_sheets: int | None = None) -> RunData:
    """Everything a report needs about `run`, as stored.

    Every finished sequence gets its stored comparison sheet and preview (render step), its
    wrist plot and its location-error plot (metrics step arrays). `max_figures` limits the plots
    to that many sequences with the largest IK wrist error; the page states the
    rule (None: every sequence). `max_sheets` is accepted for compatibility (sheets are never re-rendered now).
    """
    store, manifest = open_run(store_root, run)
    seqs = manifest.sequences
    ids = sorted(seqs)
    sequences = pd.DataFrame(
        {"status": [seqs[i]["status"] for i in ids],
         "failed_step": [seqs[i].get("failed_step") or "" for i in ids],
         "error": [seqs[i].get("error") or "" for i in ids],
         "text": [sequence_text(store, seqs[i]) for i in ids]},
        index=pd.Index(ids, name="id"))
    data = RunData(name=run, sequences=sequences, collision=metrics_frame(manifest, COLLIDE),
                   retarget=metrics_frame(manifest, RETARGET))
    cfg = manifest.data.get("config") or {}
    data.robot = str((cfg.get("robot") or {}).get("name") or "")
    steps = {step for seq in seqs.values() for step in seq.get("metrics", {})}
    data.other = {step: metrics_frame(manifest, step) for step in sorted(steps)
                  if step not in (COLLIDE, RETARGET, REFINE)}
    ok = [i for i in ids if seqs[i]["status"] == "ok" and RETARGET in seqs[i]["steps"]]
    if not ok:
        return data
    final = data.other.get(METRICS, pd.DataFrame())
    if len(final):
        counters = final.loc[final.index.intersection(ok), [k for k in VALIDATION_KEYS if k in final]]
    else:
        counters = pd.DataFrame()
    refined = metrics_frame(manifest, REFINE)
    if len(refined):
        critic = str((cfg.get("critic") or {}).get("kind") or "critic")
        data.refined[critic] = refined
        data.critic_ik[critic] = _prefixed(final, CRITIC_IK) if len(final) else pd.DataFrame()
        data.validation[critic] = counters
    else:  # the IK trajectory is the final one: its validity is the exported array's
        for key in counters:
            data.retarget.loc[counters.index, key] = counters[key]
    for sid in ok:
        sheet, preview = _render(store, seqs[sid])
        if sheet is not None:
            data.sheets[sid] = sheet
        if preview is not None:
            data.previews[sid] = preview
    error = data.retarget.loc[ok, "wrist_pos_err_mm"] if "wrist_pos_err_mm" in data.retarget \
        else pd.Series(0.0, index=ok)
    worst = error.sort_values(ascending=False, kind="stable")
    chosen = list(worst.index if max_figures is None else worst.index[:max_figures])
    if len(chosen) < len(ok):
        data.figure_rule = (f"Wrist and location plots: the {len(chosen)} of {len(ok)} finished "
                            "sequences with the largest IK-only wrist position error (`embody "
                            "report --max-figures N` draws more).")
    fps = {sid: float(seqs[sid].get("metrics", {}).get(SOURCE, {}).get("fps") or 30.0) for sid in ok}
    missing = []
    for sid in chosen:
        arrays, labels = _metrics_arrays(store, seqs[sid])
        if "wrist_reference" not in arrays:
            missing.append(sid)
            continue
        tracks = {"reference": arrays["wrist_reference"], "IK only": arrays["wrist_ik"]}
        if "wrist_refined" in arrays:
            tracks["refined"] = arrays["wrist_refined"]
        data.wrists[sid] = tracks
        data.wrist_fps[sid] = fps[sid]
        if "location_err" in arrays and "location_landmark" in labels:
            # per-frame fidelity is measured on the exported array, at `fidelity.rate_hz`
            rate = seqs[sid].get("metrics", {}).get(METRICS, {}).get("fidelity.rate_hz") or fps[sid]
            data.locations[sid] = {"err": np.asarray(arrays["location_err"]),
                                   "landmark": np.asarray(arrays["location_landmark"]),
                                   "names": list(labels["location_landmark"]), "fps": float(rate)}
    for sid in chosen:
        key = seqs[sid].get("steps", {}).get(PHYSICS)
        if key is None:
            continue
        arrays = store.read(PHYSICS, key).arrays
        if "torque_ratio" in arrays and "palm_err_mm" in arrays:
            rate = seqs[sid].get("metrics", {}).get(METRICS, {}).get("validation_rate_hz") or fps[sid]
            data.physics[sid] = {"torque_ratio": np.asarray(arrays["torque_ratio"], dtype=np.float64),
                                 "palm_err_mm": np.asarray(arrays["palm_err_mm"], dtype=np.float64),
                                 "fps": float(rate)}
    if missing:
        data.figure_rule += (f" {len(missing)} sequences have no stored wrist tracks (a run made "
                             "before the metrics step stored them: rerun `embody run` to add them).")
    unrendered = [i for i in ok if i not in data.sheets]
    if unrendered:
        data.figure_rule += (f" {len(unrendered)} finished sequences have no comparison sheet "
                             "(the run had rendering off: `embody run --render`).")
    return data


def sequence_text(store: Any, seq: dict[str, Any]) -> str:
    """The sign's text from the source motion's attrs (read without loading its arrays)."""
    key = seq.get("steps", {}).get(SOURCE)
    if key is None:
        return ""
    return str(store.attrs(SOURCE, key).get("meta", {}).get("text", ""))
