"""The default pipeline: each step is one library call plus its key ingredients.

source → collide → shape_fit (shared) → retarget → [refine] → [render] → metrics → physics. Library imports happen
inside the steps, so defining the pipeline costs nothing and never imports a stage's deps.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from embody.motion import Motion
from embody.tasks.pipeline import Context, Pipeline, Step

__all__ = ["Metrics", "default_pipeline", "warm", "SOURCE", "COLLIDE", "SHAPE_FIT", "RETARGET",
           "RETARGET_BEFORE_CRITIC", "REFINE", "RENDER", "METRICS", "PHYSICS"]


@dataclass
class Metrics:
    """The `metrics` step's result: a flat dict of numbers (attrs) and arrays: the exported
    control-rate trajectory `q_control` (float64, the exact array the validity figures describe)
    and the final trajectory's per-frame location error per hand and the human's nearest landmark."""

    metrics: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    #: Labels of the arrays (e.g. the landmark names `location_landmark` indexes); not metrics.
    labels: dict[str, list[str]] = field(default_factory=dict)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return dict(self.arrays)

    def to_attrs(self) -> dict[str, Any]:
        return {"metrics": self.metrics, "labels": self.labels}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "Metrics":
        return cls(dict(attrs.get("metrics", {})), {k: np.asarray(v) for k, v in arrays.items()},
                   {k: list(v) for k, v in attrs.get("labels", {}).items()})


def _robot_files(cfg: Any) -> list[Path]:
    """The robot definition (and MJCF override): editing them must invalidate robot steps."""
    from embody.robot import robots_dir
    files = [robots_dir(cfg.robot) / f"{cfg.robot.name}.yaml"]
    return files + ([Path(cfg.robot.mjcf_path)] if cfg.robot.mjcf_path else [])


#: Targets built in this process, by content (`_targets`); a few batches' worth.
_TARGETS: OrderedDict[bytes, Any] = OrderedDict()
_TARGETS_LOCK = threading.Lock()
#: Targets kept at least; a run keeps those of all its sequences in flight (`_targets_size`).
_TARGETS_SIZE = 32


def _targets_size(cfg: Any) -> int:
    """Targets the memo keeps: every sequence a run can have in flight (its driver keeps
    2 × workers batches going), so a batch's metrics step still finds the targets its retarget
    step built while the other batches build theirs."""
    return max(_TARGETS_SIZE, 2 * cfg.run.workers * cfg.run.batch_size)


def _digest(*arrays: Any, text: str = "") -> bytes:
    h = hashlib.blake2b(text.encode(), digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.digest()


def _targets(ctx: Context, motion: Motion, fit: Any, ik: Any, remember: bool = True) -> Any:
    """`build_targets`, computed once per process for the same motion, fit and IK config: the
    refine (and render) steps take the targets the retarget step built, instead of rebuilding
    them. Keyed by content, so a hit is exactly what a rebuild would give. `remember=False`:
    targets no later step asks for (the metrics step's IK-only baseline) are built without
    pushing the retarget step's out of the memo (in a default 24-sequence run they did so for 14
    sequences, whose metrics step then rebuilt the location-preserving targets, ~0.2 CPU-s each)."""
    from embody.retarget import build_targets
    transl = np.zeros(0) if motion.transl is None else motion.transl
    key = _digest(motion.pose, transl, motion.betas, np.asarray(motion.fps),
                  *(np.asarray(v) for v in fit.to_arrays().values()),
                  text=ik.model_dump_json() + ctx.cfg.section_json("body") + ctx.cfg.section_json("robot"))
    with _TARGETS_LOCK:
        if key in _TARGETS:
            _TARGETS.move_to_end(key)
            return _TARGETS[key]
    targets = build_targets(motion, ctx.body, fit, ctx.robot, ik)
    if not remember:
        return targets
    with _TARGETS_LOCK:
        _TARGETS[key] = targets
        while len(_TARGETS) > _targets_size(ctx.cfg):
            _TARGETS.popitem(last=False)
    return targets


#: Human tracks at the control rate built in this process, by content (`_human_track`).
_HUMANS: OrderedDict[bytes, Any] = OrderedDict()


def _human_track(ctx: Context, motion: Motion, rate: float, times: np.ndarray | None = None) -> Any:
    """The human's fidelity track resampled to `rate` Hz, or at `times` (s: a retimed export's
    source times, `IKSolution.source_time`), built once per process for the same motion, body
    and times: the metrics step builds it, the physics step scores its simulated motion against
    the same one (~half of a sequence's fidelity cost is building it)."""
    from embody.metrics.embodiments import human_track
    from embody.metrics.fidelity import resample_track
    transl = np.zeros(0) if motion.transl is None else motion.transl
    key = _digest(motion.pose, transl, motion.betas, np.asarray([motion.fps, rate]),
                  *(() if times is None else (np.asarray(times, dtype=np.float64),)),
                  text=ctx.cfg.section_json("body"))
    with _TARGETS_LOCK:
        if key in _HUMANS:
            _HUMANS.move_to_end(key)
            return _HUMANS[key]
    human = resample_track(human_track(motion, ctx.body), rate, times)
    with _TARGETS_LOCK:
        _HUMANS[key] = human
        while len(_HUMANS) > _targets_size(ctx.cfg):
            _HUMANS.popitem(last=False)
    return human


def _load_source(ctx: Context, inputs: dict[str, Any]) -> Motion:
    """The sequence with the `io` overrides (fps, up axis, hands) applied and within the `io`
    bounds; `io` is in its key."""
    io = ctx.cfg.io
    return inputs["ref"].load(fps=io.fps, up_axis=io.up_axis, hands=io.hands, limits=io)


def _source_metrics(motion: Motion) -> dict[str, Any]:
    from embody.io.conventions import layout_warnings

    out: dict[str, Any] = {"frames": motion.num_frames, "fps": motion.fps}
    warnings = layout_warnings(motion.source.provenance)
    if warnings:  # the run's closing summary names each once (`flows.verdicts.layout_warnings`)
        out["layout_warnings"] = " | ".join(warnings)
    return out


def _collide(ctx: Context, inputs: dict[str, Any]) -> Any:
    from embody.collision.windows import mitigate_windowed
    return mitigate_windowed(inputs["source"], ctx.body, ctx.cfg.collision)


def _collision_result(arrays: dict[str, Any], attrs: dict[str, Any]) -> Any:
    from embody.collision import CollisionResult
    return CollisionResult.from_arrays(arrays, attrs)


def _shape_fit(ctx: Context, inputs: dict[str, Any]) -> Any:
    from embody.retarget import shape_fit
    return shape_fit(ctx.robot, ctx.body, ctx.cfg.ik)


def _shape_fit_result(arrays: dict[str, Any], attrs: dict[str, Any]) -> Any:
    from embody.retarget import ShapeFit
    return ShapeFit.from_arrays(arrays, attrs)


def _retarget(ctx: Context, inputs: dict[str, Any]) -> Any:
    from embody.retarget.windows import solve_windowed
    targets = _targets(ctx, inputs["collide"].motion, inputs["shape_fit"], ctx.cfg.ik)
    return solve_windowed(ctx.robot, targets, ctx.cfg.ik)


def _retarget_before_critic(ctx: Context, inputs: dict[str, Any]) -> Any:
    """The retarget step when the critic follows: the same solve, its control-rate array without
    the torque and ZMP retiming (`ik.without_dynamics_limits`), which the refine step runs once, on
    the round it chooses, the array exported (~2 s a call, on every round before)."""
    from embody.retarget.ik import without_dynamics_limits
    from embody.retarget.windows import solve_windowed
    targets = _targets(ctx, inputs["collide"].motion, inputs["shape_fit"], ctx.cfg.ik)
    return solve_windowed(ctx.robot, targets, without_dynamics_limits(ctx.cfg.ik))


def _ik_solution(arrays: dict[str, Any], attrs: dict[str, Any]) -> Any:
    from embody.retarget import IKSolution
    return IKSolution.from_arrays(arrays, attrs)


def _refine(ctx: Context, inputs: dict[str, Any]) -> Any:
    """Critic rounds after IK, each re-solve warm-started from the previous round's solution;
    the reference targets are the retarget step's (`_targets`: reused in this process, else
    rebuilt identically)."""
    from embody.critic import refine
    motion, fit = inputs["collide"].motion, inputs["shape_fit"]
    targets = _targets(ctx, motion, fit, ctx.cfg.ik)
    return refine(motion, ctx.body, fit, ctx.robot, targets, inputs["retarget"], ctx.cfg.critic,
                  ctx.cfg.ik, ctx.cfg.render, critic=ctx.critic, ik_kinematic=True)


def _refine_metrics(result: Any) -> dict[str, Any]:
    """The chosen round's metrics (its `control_*` counts: its exported array's), the critic's
    verdict on the result (`accepted`: on the exported array too, when judged again) and, when
    it judged the export, that judgement's figures (`export.*`)."""
    out = {**result.final.metrics, "accepted": bool(result.accepted),
           "rounds": len(result.rounds) - 1, "chosen_round": int(result.final.index)}
    if result.export_accepted is not None:
        out["export_accepted"] = bool(result.export_accepted)
        out.update({f"export.{k}": v for k, v in result.export.get("metrics", {}).items()
                    if isinstance(v, (int, float, bool))})
    return out


def _refine_result(arrays: dict[str, Any], attrs: dict[str, Any]) -> Any:
    from embody.critic import RefineResult
    return RefineResult.from_arrays(arrays, attrs)


def _render(ctx: Context, inputs: dict[str, Any]) -> Any:
    """The final trajectory (refined when the critic ran) beside the reference body."""
    from embody.render import select_keyframes
    from embody.render.record import render_sequence
    motion, fit, refined = inputs["collide"].motion, inputs["shape_fit"], inputs.get("refine")
    if refined is not None:  # the frames the critic saw
        q, keyframes = refined.q, refined.keyframes
    else:
        q = inputs["retarget"].q
        targets = _targets(ctx, motion, fit, ctx.cfg.ik)
        keyframes = select_keyframes(targets.wrist_pos, ctx.cfg.render.keyframes)
    title = f"{motion.meta.get('id', '')}: {'refined' if refined is not None else 'IK only'}"
    return render_sequence(motion, ctx.body, fit, ctx.robot, q, keyframes, ctx.cfg.render, title)


def _render_result(arrays: dict[str, Any], attrs: dict[str, Any]) -> Any:
    from embody.render.record import SequenceRender
    return SequenceRender.from_arrays(arrays, attrs)


def _render_metrics(result: Any) -> dict[str, Any]:
    return {"keyframes": int(len(result.keyframes)), "preview": result.preview_suffix or ""}


def _fidelity(ctx: Context, inputs: dict[str, Any], final_control: np.ndarray, final_time: np.ndarray
              ) -> tuple[dict[str, Any], dict[str, np.ndarray], list[str]]:
    """Sign fidelity against the human that IK retargets (after collision mitigation), per row of
    Table III: `ik` (shape-fit targets only; solved here as the baseline when the run used
    location-preserving targets), `preserving` (the retarget step then) and `refined`.

    Each row is measured on its control-rate array (`q_control`; the final row's is
    `final_control`, the array stored and exported), against the human track resampled to the same
    times (`resample_track`): the robot a user receives, not the source-rate solve. Only the final
    row's array went through the torque and ZMP retiming, so it is scored against the human at
    its samples' source times (`final_time`): the same instant of the sign, whatever the
    slowdown. With the critic, the `preserving` row is the
    retarget step's kinematic array (`RETARGET_BEFORE_CRITIC`), as the `ik` baseline's is, and
    `refined_kinematic` the chosen round's kinematic array (the same chain without the solve), so
    the critic's effect (`preserving` → `refined_kinematic`) and the solve's (→ `refined`) are
    each measured apart."""
    from embody.metrics.embodiments import scored_robot_track
    from embody.metrics.fidelity import LOCATION_LANDMARKS, compare_with
    from embody.retarget import solve
    from embody.retarget.ik import exported_control, same_problem, without_dynamics_limits
    from embody.retarget.validation import validation_counts
    motion, ik, cfg = inputs["collide"].motion, inputs["retarget"], ctx.cfg
    human = _human_track(ctx, motion, ik.control_rate_hz)
    rows: dict[str, np.ndarray] = {}
    out: dict[str, Any] = {}
    if cfg.ik.location_preserving and cfg.fidelity.baseline:
        # the plain retargeter the paper compares with: no anchored targets, and its 50 Hz array
        # not held inside the torque and ZMP limits (that solve is the export's, not a baseline's)
        plain = cfg.ik.model_copy(update={"location_preserving": False, "dynamics_limits": False})
        plain_targets = _targets(ctx, motion, inputs["shape_fit"], plain, remember=False)
        # nothing anchored: the retarget step already solved this very problem
        same = same_problem(plain_targets, _targets(ctx, motion, inputs["shape_fit"], cfg.ik))
        base = ik if same else solve(ctx.robot, plain_targets, plain)
        rows["ik"] = base.q_control
        # the solve counted MuJoCo contacts of its own q: not counted twice
        out.update({f"fidelity.ik.{k}": v for k, v in validation_counts(
            ctx.robot, base.q, ik.fps, base.frame_metrics.get("self_contacts")).items()})
        out["fidelity.ik.mean_jerk"] = base.metrics["jerk"]
    rows["preserving" if cfg.ik.location_preserving else "ik"] = np.asarray(ik.q_control)
    if "refine" in inputs and cfg.ik.dynamics_limits:
        # the chosen round's kinematic array: against `preserving` (kinematic too) the critic's
        # own effect; against `refined` what the torque and ZMP retiming cost the sign
        final = inputs["refine"].final
        rows["refined_kinematic"] = (np.asarray(final.q_kinematic) if final.q_kinematic is not None else
                                     exported_control(ctx.robot, final.q, ik.fps, without_dynamics_limits(cfg.ik))[0])
    # the final row is the array stored and exported
    final_row = "refined" if "refine" in inputs else list(rows)[-1]
    rows[final_row] = final_control
    uniform = len(final_time) == len(final_control) and np.allclose(
        final_time, np.arange(len(final_control)) / ik.control_rate_hz, rtol=0.0, atol=1e-9)
    final_human = human if uniform else _human_track(ctx, motion, ik.control_rate_hz, final_time)
    frames: dict[str, np.ndarray] = {}
    scored: list[tuple[np.ndarray, Any]] = []
    for row, q in rows.items():
        against = final_human if row == final_row else human
        # a row equal to an earlier one (the critic kept the IK solution) is not scored twice
        same = next((r for p, r in scored if p.shape == q.shape and np.array_equal(p, q)), None)
        if same is None:
            robot = scored_robot_track(ctx.robot, q, ik.control_rate_hz, against, cfg.fidelity)
            same = compare_with(against, robot, cfg.fidelity)
        per_frame, metrics = same
        scored.append((q, same))
        out.update({f"fidelity.{row}.{k}": v for k, v in metrics.items()})
        frames = {"location_err": per_frame["location_err"], "location_landmark": per_frame["location_landmark"]}
        names = [n for n in LOCATION_LANDMARKS if against.has(n) and robot.has(n)]  # what it indexes
    out["fidelity.final"] = list(rows)[-1]
    out["fidelity.rate_hz"] = float(ik.control_rate_hz)  # per-frame fidelity arrays are at this rate
    return out, frames, names


def _report_tracks(ctx: Context, inputs: dict[str, Any]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """What the report plots and tabulates but cannot compute (it never loads the robot): the
    wrist tracks (T,2,3, torso frame, m) of the IK's reference, the IK-only and the refined
    trajectory, and the critic's metrics of its IK-only round (`critic_ik.*`)."""
    from embody.critic.refine import robot_wrists
    refined = inputs.get("refine")
    if refined is not None:
        first, final = refined.ik_only, refined.final

        def wrists(r: Any) -> np.ndarray:  # the critic's own FK of that round, when stored
            return r.wrist_pos if r.wrist_pos is not None else robot_wrists(ctx.robot, r.q)[0]
        arrays = {"wrist_reference": first.target_pos, "wrist_ik": wrists(first),
                  "wrist_refined": wrists(final)}
        out: dict[str, Any] = {f"critic_ik.{k}": v for k, v in first.metrics.items()
                               if isinstance(v, (int, float, bool))}
        out["critic_ik.accepted"] = bool(first.accepted)
    else:
        targets = _targets(ctx, inputs["collide"].motion, inputs["shape_fit"], ctx.cfg.ik)
        arrays = {"wrist_reference": targets.wrist_pos, "wrist_ik": robot_wrists(ctx.robot, inputs["retarget"].q)[0]}
        out = {}
    return out, {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()}


def _control_counts(ik: Any, q_control: np.ndarray) -> dict[str, float] | None:
    """`validation_counts` of the control-rate array the IK's solve (or the refine step's chosen
    round) made and verified (its `control_*` metrics), when `q_control` is that array; else None."""
    from embody.verdicts import VALIDATION_KEYS as names
    if ik.q_control is None or not all(f"control_{k}" in ik.metrics for k in names):
        return None
    if np.shape(q_control) != np.shape(ik.q_control) or not np.array_equal(q_control, ik.q_control):
        return None
    return {k: float(ik.metrics[f"control_{k}"]) for k in names}


def _trajectory_metrics(ctx: Context, inputs: dict[str, Any]) -> Metrics:
    """Smoothness, MuJoCo-verified validity and sign fidelity of the final joint trajectory (the
    refined one when the critic ran). Validity is measured on the exact control-rate array
    `embody export` writes (stored here as `q_control`); the source-rate counters go under
    `source_*`. Every number the report's tables and the export read. Torch on one thread
    (`torch_threads(1)`, as `collision.threads` for the optimiser): the step's torch work (the IK
    baseline's chain FK, the human's FK) is many small ops, where a second OpenMP thread only
    adds barrier waits (2 threads: 4.6 CPU-s per sequence at load 4, 1 thread: 0.67, the same
    bits)."""
    from embody.device import torch_threads
    with torch_threads(1):
        return _measure(ctx, inputs)


def _measure(ctx: Context, inputs: dict[str, Any]) -> Metrics:
    """`_trajectory_metrics`' work."""
    from embody.metrics import mean_jerk
    from embody.retarget.dynamics_limits import duration_ratio, time_stretch
    from embody.retarget.ik import exported_control
    from embody.retarget.validation import validation_counts
    ik = inputs["retarget"]
    owner = ik  # what made the exported array, and counted it
    if "refine" in inputs:
        final = owner = inputs["refine"].final
        q = np.asarray(final.q, dtype=np.float64)
        if final.q_control is not None and final.source_time is not None:  # the refine step's export
            q_control = np.asarray(final.q_control, dtype=np.float64)
            source_time = np.asarray(final.source_time, dtype=np.float64)
        else:
            q_control, _, source_time = exported_control(ctx.robot, q, ik.fps, ctx.cfg.ik)
    else:
        q, q_control = np.asarray(ik.q, dtype=np.float64), np.asarray(ik.q_control, np.float64)
        source_time = np.asarray(ik.source_time, dtype=np.float64)
    # the IK's solve already counted MuJoCo contacts of its own arrays: not counted twice
    ik_contacts = ik.frame_metrics.get("self_contacts")
    source = validation_counts(ctx.robot, q, ik.fps, ik_contacts
                               if ik_contacts is not None and np.array_equal(q, ik.q) else None)
    control = _control_counts(owner, q_control)
    if control is None:
        control = validation_counts(ctx.robot, q_control, ik.control_rate_hz)
    fidelity, frames, names = _fidelity(ctx, inputs, q_control, source_time)
    tracked, tracks = _report_tracks(ctx, inputs)
    rate = float(ik.control_rate_hz)
    return Metrics({"frames": int(q.shape[0]), "joints": int(q.shape[-1]),
                    "duration_s": float(q.shape[0] / ik.fps), "mean_jerk": mean_jerk(q, ik.fps),
                    "final": "refine" if "refine" in inputs else "retarget",
                    "control_frames": int(q_control.shape[0]),
                    "validation_rate_hz": float(ik.control_rate_hz),
                    "time_stretch_max": time_stretch(source_time, rate),
                    "duration_ratio": duration_ratio(source_time, rate),
                    **control,
                    **{f"source_{k}": v for k, v in source.items()}, **fidelity, **tracked},
                   {"q_control": q_control, "source_time": source_time, **frames, **tracks},
                   {"location_landmark": names})


def _physics(ctx: Context, inputs: dict[str, Any]) -> Any:
    """The exported control-rate array (`metrics`' `q_control`) replayed in MuJoCo with the
    robot's actuation (`embody.physics`): torque, tracking, contacts, balance, and sign fidelity
    of the simulated motion against the same human track the metrics step scores."""
    from embody.device import torch_threads
    from embody.physics import PhysicsResult, evaluate
    if ctx.robot.spec.actuation is None:  # a user robot without gains: nothing to replay
        return PhysicsResult({"skipped": "the robot YAML has no actuation section"})
    metrics = inputs["metrics"]
    q = np.asarray(metrics.arrays["q_control"], dtype=np.float64)
    rate = float(metrics.metrics.get("validation_rate_hz", metrics.metrics.get("fidelity.rate_hz", 50.0)))
    times = metrics.arrays.get("source_time")  # the retimed export's samples' source times
    with torch_threads(1):
        human = _human_track(ctx, inputs["collide"].motion, rate, times)
        return evaluate(ctx.robot, q, rate, human, ctx.cfg.fidelity)


def _physics_result(arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> Any:
    from embody.physics import PhysicsResult
    return PhysicsResult.from_arrays(arrays, attrs)


# The motion, y-up with absolute hands; frame rate, up axis and hands from the file, the
# dataset's documented default, or the `io` overrides.
SOURCE = Step("source", "3", ("io",), _load_source, Motion.from_arrays, metrics=_source_metrics)
# The collision-mitigated motion: masked Adam on the volumetric energy, depth-guided polish and a
# mesh-judged pull-back; metrics include the mesh penetration depth before and after.
COLLIDE = Step("collide", "14", ("body", "collision"), _collide, _collision_result, (SOURCE,))
# Betas and scale fitted to the robot's proportions, once per robot and body (shared).
SHAPE_FIT = Step("shape_fit", "1", ("body", "robot", "ik"), _shape_fit, _shape_fit_result,
                 shared=True, files=_robot_files)
# The whole-sequence IK on location-preserving targets; its 50 Hz array clear of contacts and, retimed
# where needed, inside the effort limits and ZMP margin (`retarget.control`,
# `retarget.dynamics_limits`), with its counts and its samples' source times.
RETARGET = Step("retarget", "27", ("body", "robot", "ik"), _retarget, _ik_solution,
                (COLLIDE, SHAPE_FIT), files=_robot_files)
# The same solve when the critic follows: its 50 Hz array kinematic only (contacts, joint box,
# velocities; counted as such), the torque and ZMP retiming left to the round the critic chooses.
RETARGET_BEFORE_CRITIC = Step("retarget", "26+critic", ("body", "robot", "ik"), _retarget_before_critic,
                              _ik_solution, (COLLIDE, SHAPE_FIT), files=_robot_files)
# Every critic round's IK solution, action and comparison sheet (the re-solves' 50 Hz arrays
# kinematic only); the chosen round's exported control-rate array (torque and ZMP retiming
# included, once) with its validation counts, the critic's verdict on that array, and the
# rounds' wrist positions, which `metrics` reuses.
REFINE = Step("refine", "29", ("body", "robot", "ik", "render", "critic"), _refine,
              _refine_result, (COLLIDE, SHAPE_FIT, RETARGET_BEFORE_CRITIC), metrics=_refine_metrics,
              files=_robot_files)
# The comparison sheet and the 15 fps preview of the reference (a MuJoCo skin) and the robot.
# Later steps read only its stored result (the report), none of its process's memos.
RENDER = Step("render", "4", ("body", "robot", "render"), _render, _render_result,
              (COLLIDE, SHAPE_FIT, RETARGET), metrics=_render_metrics, files=_robot_files,
              affinity=False)
RENDER_REFINED = Step("render", "4", ("body", "robot", "render"), _render, _render_result,
                      (COLLIDE, SHAPE_FIT, RETARGET_BEFORE_CRITIC, REFINE), metrics=_render_metrics,
                      files=_robot_files, affinity=False)
# The exported control-rate array, its validation counts (torque included) and jerk, Table III's
# sign fidelity on it against the mitigated human, and the report's wrist tracks.
METRICS = Step("metrics", "17", ("body", "robot", "ik", "fidelity"), _trajectory_metrics,
               Metrics.from_arrays, (COLLIDE, SHAPE_FIT, RETARGET), files=_robot_files)
METRICS_REFINED = Step("metrics", "17", ("body", "robot", "ik", "fidelity"), _trajectory_metrics,
                       Metrics.from_arrays, (COLLIDE, SHAPE_FIT, RETARGET_BEFORE_CRITIC, REFINE),
                       files=_robot_files)

# The exported array replayed in MuJoCo with the robot's actuation, fixed base and standing.
PHYSICS = Step("physics", "5", ("body", "robot", "fidelity"), _physics, _physics_result,
               (COLLIDE, METRICS), files=_robot_files)
PHYSICS_REFINED = Step("physics", "5", ("body", "robot", "fidelity"), _physics, _physics_result,
                       (COLLIDE, METRICS_REFINED), files=_robot_files)


def default_pipeline(critic: bool = False, render: bool = False) -> Pipeline:
    """The full chain; `critic` adds the refinement step after IK, `render` the comparison
    sheet (and preview) of the final trajectory."""
    steps: list[Step] = [COLLIDE, SHAPE_FIT, RETARGET_BEFORE_CRITIC if critic else RETARGET]
    if critic:
        steps.append(REFINE)
    if render:
        steps.append(RENDER_REFINED if critic else RENDER)
    steps.append(METRICS_REFINED if critic else METRICS)
    steps.append(PHYSICS_REFINED if critic else PHYSICS)
    return Pipeline(SOURCE, tuple(steps))


#: What each step imports and builds on its first call in a process, by step name.
_WARM_MODULES = {"collide": ("embody.collision.windows", "embody.body.sparse_skin"),
                 "shape_fit": ("embody.retarget",),
                 "retarget": ("embody.retarget.windows", "embody.retarget.ik"),
                 "refine": ("embody.critic", "embody.critic.refine"),
                 "render": ("embody.render", "embody.render.record"),
                 "metrics": ("embody.metrics", "embody.metrics.fidelity",
                             "embody.metrics.embodiments", "embody.retarget.control",
                             "embody.retarget.validation"),
                 "physics": ("embody.physics",)}


def warm(ctx: Context, pipeline: Pipeline) -> None:
    """Import what `pipeline`'s steps import, load their cached compiled kernels and build the
    models they share (body, robot, critic: those whose config section a step reads), so a
    thread runner's workers start computing at once instead of each importing and loading the
    same (the flow calls this while Prefect's server boots: `flows.ephemeral`)."""
    import importlib

    from embody.jit_cache import load_cached_kernels
    names = set(pipeline.names)
    for name in pipeline.names:
        for module in _WARM_MODULES.get(name, ()):
            importlib.import_module(module)
    load_cached_kernels()
    sections = {section for step in pipeline.steps for section in step.sections}
    for model in ("body", "robot", "critic"):
        if model in sections:
            getattr(ctx, model)
    if "collide" in names:  # the judge's mesh groups (per body)
        from embody.collision.depth import depth_mesh
        depth_mesh(ctx.body, ctx.cfg.collision.allow_pairs)
    if "physics" in names and ctx.robot.spec.actuation is not None:  # the robot's replay models
        from embody.physics.replay import fixed_model, standing_model
        fixed_model(ctx.robot)
        standing_model(ctx.robot)
    if "render" in names:  # the robot as drawn (decimated meshes), before a worker forks
        from embody.render.scene import prepared_robot_model
        prepared_robot_model(ctx.robot, ctx.cfg.render, ctx.robot.spec.torso_body)
    if "retarget" in names:  # the robot's proxies and hand-clearance tables (per robot)
        from types import SimpleNamespace

        from embody.retarget.hand_clearance import CHANNELS, hand_clearance_term
        from embody.robot.proxies import robot_proxies
        robot_proxies(ctx.robot)
        hand_clearance_term(ctx.robot, SimpleNamespace(hand_gap=np.ones((1, len(CHANNELS)))), 1.0)
