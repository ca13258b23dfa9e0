"""The critic refinement loop: IK-only → critique → offset the targets → re-solve, per round.

The critic always compares the robot against the *reference* (the human's targets), while the
primitives offset the *working* IK targets; offsets accumulate there across rounds. So a robot
that misses a target by 10 cm gets its target moved 10 cm further, not its reference.

Each round's re-solve makes its control-rate array without the torque and ZMP retiming
(`retarget.dynamics_limits`, seconds per call): the critic judges a round's source-rate solve,
which that solve never changes. It runs once, after the choice, on the chosen round: the array
the pipeline exports (`RoundRecord.q_control`). When the critic had accepted the chosen round, it
judges that exported array again (read at the source frames, `_at_frames`), and the result is
accepted only if the critic accepts it too (`RefineResult.export`): the verdict describes the
trajectory a user receives, not an array before its limits.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd
import torch

from embody.config.critic import CriticConfig
from embody.config.render import RenderConfig
from embody.critic.action import Action, Limits
from embody.critic.base import Critic, CritiqueContext
from embody.critic.primitives import apply_primitives
from embody.metrics.trajectory import dtw_distance, position_error, rotation_error_deg

log = logging.getLogger(__name__)

WRISTS = ["left_wrist", "right_wrist"]


def make_critic(cfg: CriticConfig) -> Critic:
    """The configured critic (the VLM one checks its API key here)."""
    if cfg.kind == "vlm":
        from embody.critic.vlm import VLMCritic

        return VLMCritic(cfg.vlm)
    from embody.critic.geometric import GeometricCritic

    return GeometricCritic(cfg)


def robot_wrists(robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wrist positions (T,2,3) and rotations (T,2,3,3) of joint trajectories, torso frame."""
    with torch.no_grad():
        pos, rot = robot.link_points(torch.as_tensor(np.asarray(q), dtype=torch.float64), WRISTS)
    return pos.cpu().numpy(), rot.cpu().numpy()


def wrist_metrics(ref_pos: np.ndarray, ref_rot: np.ndarray, pos: np.ndarray, rot: np.ndarray,
                  arm_length: float) -> dict[str, float]:
    """Signing-space errors of the robot against the reference, both wrists pooled."""
    err = position_error(pos, ref_pos) * 1000.0
    ang = rotation_error_deg(rot, ref_rot)
    dtw = [dtw_distance(pos[:, s], ref_pos[:, s]) * 1000.0 for s in range(2)]
    offset = np.linalg.norm((ref_pos - pos).mean(axis=0), axis=-1)
    return {
        "wrist_mm_mean": float(err.mean()), "wrist_mm_p95": float(np.percentile(err, 95)),
        "wrist_deg_mean": float(ang.mean()), "wrist_deg_p95": float(np.percentile(ang, 95)),
        "wrist_dtw_mm": float(np.mean(dtw)),
        "wrist_offset_arm": float(offset.max() / arm_length),
    }


@dataclass
class RoundRecord:
    """One round: the working targets solved for, the solution, its metrics and the critique."""

    index: int
    q: np.ndarray
    target_pos: np.ndarray
    target_rot: np.ndarray
    metrics: dict[str, float]
    #: The critic's action on this round's solution (None when it was not critiqued).
    action: dict[str, Any] | None = None
    #: Render name → {"sha256": ..., "path": ...}.
    renders: dict[str, dict[str, str | None]] = field(default_factory=dict)
    #: The critic's request/response record (VLM), images by hash.
    exchange: dict[str, Any] = field(default_factory=dict)
    #: The control-rate array of `q`: the re-solve's kinematic one during the loop; for the
    #: chosen round, the exported one (torque and ZMP limits included), the only one stored.
    q_control: np.ndarray | None = None
    #: The chosen round's control-rate array as its solve made it (the re-solves' and the
    #: pipeline's retarget step's: kinematic, before the torque and ZMP retiming made `q_control`;
    #: round 0's is the given IK solution's), kept so the metrics step scores the solve apart.
    q_kinematic: np.ndarray | None = None
    #: (N,) each `q_control` sample's time (s) on the source's timeline (the chosen round's
    #: export: the torque and ZMP limits may have slowed it down, `dynamics_limits.retime_dynamics`).
    source_time: np.ndarray | None = None
    #: The robot's wrist positions (T,2,3, torso frame) of `q`, as the critic measured them
    #: (stored, so the metrics step's report tracks need no second FK pass).
    wrist_pos: np.ndarray | None = None

    @property
    def accepted(self) -> bool | None:
        return None if self.action is None else bool(self.action["valid"] and self.action["verdict"] == "accept")


@dataclass
class RefineResult:
    rounds: list[RoundRecord]
    joint_names: list[str]
    keyframes: np.ndarray
    critic: str
    #: Index of the round that is the result (`critic.keep`); -1 = the last.
    chosen: int = -1
    #: The critic's judgement of the chosen round's exported array (read at the source frames),
    #: when it had accepted the round: {"metrics": ..., "action": ..., "exchange": ...}; else {}.
    export: dict[str, Any] = field(default_factory=dict)

    @property
    def ik_only(self) -> RoundRecord:
        return self.rounds[0]

    @property
    def final(self) -> RoundRecord:
        return self.rounds[self.chosen]

    @property
    def q(self) -> np.ndarray:
        return self.final.q

    @property
    def export_accepted(self) -> bool | None:
        """The critic's verdict on the exported array (None when it was not judged again)."""
        action = self.export.get("action")
        return None if action is None else bool(action["valid"] and action["verdict"] == "accept")

    @property
    def accepted(self) -> bool:
        """The critic accepted the result: its chosen round and, judged again, that round's
        exported array (`critic.keep` picks an accepted round when there is one)."""
        return bool(self.final.accepted) and self.export_accepted is not False

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {"q": np.stack([r.q for r in self.rounds]),
                  "target_pos": np.stack([r.target_pos for r in self.rounds]),
                  "target_rot": np.stack([r.target_rot for r in self.rounds]),
                  "keyframes": np.asarray(self.keyframes, dtype=np.int64)}
        if self.final.q_control is not None:
            arrays["final_q_control"] = np.asarray(self.final.q_control, dtype=np.float64)
        if self.final.source_time is not None:
            arrays["final_source_time"] = np.asarray(self.final.source_time, dtype=np.float64)
        if self.final.q_kinematic is not None:
            arrays["final_q_kinematic"] = np.asarray(self.final.q_kinematic, dtype=np.float64)
        if all(r.wrist_pos is not None for r in self.rounds):
            arrays["wrist_pos"] = np.stack([np.asarray(r.wrist_pos, dtype=np.float64) for r in self.rounds])
        return arrays

    def to_attrs(self) -> dict[str, Any]:
        rounds = [{"index": r.index, "metrics": r.metrics, "action": r.action,
                   "accepted": r.accepted, "renders": r.renders, "exchange": r.exchange}
                  for r in self.rounds]
        return json.loads(json.dumps({"joint_names": list(self.joint_names), "critic": self.critic,
                                      "accepted": self.accepted, "rounds": rounds,
                                      "chosen": self.chosen, "export": self.export}))

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> "RefineResult":
        rounds = [RoundRecord(index=a["index"], q=np.asarray(arrays["q"][i]),
                              target_pos=np.asarray(arrays["target_pos"][i]),
                              target_rot=np.asarray(arrays["target_rot"][i]),
                              metrics=dict(a["metrics"]), action=a["action"],
                              renders=dict(a["renders"]), exchange=dict(a["exchange"]))
                  for i, a in enumerate(attrs["rounds"])]
        result = cls(rounds, list(attrs["joint_names"]), np.asarray(arrays["keyframes"]),
                     attrs["critic"], int(attrs.get("chosen", -1)), dict(attrs.get("export") or {}))
        if "final_q_control" in arrays:
            result.final.q_control = np.asarray(arrays["final_q_control"])
        if "final_source_time" in arrays:
            result.final.source_time = np.asarray(arrays["final_source_time"])
        if "final_q_kinematic" in arrays:
            result.final.q_kinematic = np.asarray(arrays["final_q_kinematic"])
        if "wrist_pos" in arrays:
            for r, pos in zip(rounds, np.asarray(arrays["wrist_pos"])):
                r.wrist_pos = pos
        return result


class _Renders:
    """Lazily opened renderer plus the reference keyframe images (rendered once per sequence)."""

    def __init__(self, motion, body, fit, robot, cfg: RenderConfig, keyframes: np.ndarray) -> None:
        self.motion, self.body, self.fit, self.robot, self.cfg = motion, body, fit, robot, cfg
        self.keyframes = keyframes
        self._renderer = None
        self._reference: dict[str, np.ndarray] | None = None

    @property
    def renderer(self):
        if self._renderer is None:
            from embody.render.compare import open_renderer

            self._renderer = open_renderer(self.robot, self.body, self.fit, self.cfg)
        return self._renderer

    def comparison(self, q: np.ndarray):
        from embody.render.compare import render_comparison

        # the reference drawn as the render step draws it (`draw_reference`: the bound skin)
        comp = render_comparison(self.renderer, self.cfg, self.keyframes, self.motion.fps, q,
                                 self._reference, motion=self.motion)
        self._reference = comp.reference
        return comp

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _store_png(data: bytes, out_dir: Path | None, name: str) -> dict[str, str | None]:
    from embody.critic.vlm import sha256

    path = None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / name).write_bytes(data)
        path = name
    return {"sha256": sha256(data), "path": path}


def refine(motion, body, fit, robot, targets, ik_solution, cfg_critic: CriticConfig, cfg_ik,
           cfg_render: RenderConfig, out_dir: str | Path | None = None,
           critic: Critic | None = None, ik_targets=None,
           ik_kinematic: bool = False) -> RefineResult:
    """Run up to `cfg_critic.rounds` critique-and-re-solve rounds after the IK-only solution.

    `targets` is the reference; `ik_targets` the targets `ik_solution` was solved for (default
    `targets`; differs when resuming, or in tests that plant an offset). `critic` lets a run share
    one critic (and so one VLM request budget) across sequences. Renders are made only when the critic looks at images, plus the final round's sheet and
    preview when `out_dir` is given (paths in the record are relative to `out_dir`).
    The re-solves make no torque and ZMP retiming; the chosen round's exported array does
    (`cfg_ik.dynamics_limits`), once, and an accepted round's export is judged again.
    `ik_kinematic`: `ik_solution`'s control-rate array was made `without_dynamics_limits(cfg_ik)`
    (the pipeline's retarget step before the critic), so the export of round 0 starts from it, as
    a re-solve's does, instead of repeating its resample and contact repair.
    """
    from embody.render.keyframes import select_keyframes
    from embody.retarget import solve
    from embody.retarget.ik import control_counts, exported_control, without_dynamics_limits

    out = Path(out_dir) if out_dir is not None else None
    critic = critic or make_critic(cfg_critic)
    judge = (_HumanJudge(motion, body, robot, targets, cfg_critic, cfg_ik)
             if body is not None and robot.spec.landmarks else None)
    ref_pos = np.asarray(targets.wrist_pos, dtype=np.float64)
    ref_rot = np.asarray(targets.wrist_rot, dtype=np.float64)
    limits = Limits(targets.num_frames, cfg_critic.position_step_m, cfg_critic.angle_step_deg,
                    cfg_critic.max_position_m, cfg_critic.max_angle_deg)
    blend = int(round(cfg_critic.blend_s * targets.fps))
    keyframes = select_keyframes(ref_pos, cfg_render.keyframes)
    renders = _Renders(motion, body, fit, robot, cfg_render, keyframes)
    working, solution = ik_targets if ik_targets is not None else targets, ik_solution
    cfg_rounds = without_dynamics_limits(cfg_ik)  # the export's solve runs on the chosen round only
    rounds: list[RoundRecord] = []
    resolved: set[int] = set()  # the rounds whose solution a re-solve here made (kinematic)
    solved_here = False

    def critique(index: int, q: np.ndarray, pos: np.ndarray, rot: np.ndarray, location_offset: Any,
                 fidelity: dict[str, float], renders_seen: dict[str, Any],
                 label: str) -> tuple[Action, CritiqueContext]:
        """The critic's action on trajectory q (source frames) of round `index`, and what it was
        shown; the renders it looked at go into `renders_seen`, named after `label`."""
        context = CritiqueContext(index, targets.fps, targets.arm_length, ref_pos, ref_rot,
                                  pos, rot, limits, keyframes=keyframes.tolist(),
                                  text=str(motion.meta.get("text", "")), location_offset=location_offset,
                                  fidelity=fidelity, body_scale=robot.body_scale if judge else 0.0,
                                  hand_fidelity=judge.hands if judge is not None else {},
                                  reach_blocked=judge.blocked if judge is not None else None)
        if critic.needs_images:
            comp = renders.comparison(q)
            context.sheet_png = comp.sheet_png(f"{label} {index}")
            context.keyframe_pngs = comp.keyframe_pngs()
            renders_seen["sheet"] = _store_png(context.sheet_png, out, f"sheet_{label}{index}.png")
            for k, png in zip(keyframes, context.keyframe_pngs):
                renders_seen[f"keyframe_{k}"] = _store_png(png, out, f"{label}{index}_f{k}.png")
        return critic.critique(context), context

    try:
        for index in range(cfg_critic.rounds + 1):
            q = np.asarray(solution.q, dtype=np.float64)
            pos, rot = robot_wrists(robot, q)
            record = RoundRecord(index, q, np.asarray(working.wrist_pos), np.asarray(working.wrist_rot),
                                 wrist_metrics(ref_pos, ref_rot, pos, rot, targets.arm_length),
                                 q_control=getattr(solution, "q_control", None), wrist_pos=pos)
            if solved_here:
                resolved.add(index)
            location_offset, fidelity = judge(q) if judge is not None else (None, {})
            record.metrics.update(fidelity)
            rounds.append(record)
            last = index == cfg_critic.rounds
            if last and critic.needs_images:  # a VLM verdict nobody acts on is not worth a request
                break
            action, context = critique(index, q, pos, rot, location_offset, fidelity, record.renders, "round")
            if action.valid and not action.accepted and not action.primitives and not last:
                action = _with_reason_primitives(action, context, cfg_critic)
            record.action = action.to_json()
            record.exchange = context.record
            log.info("round %d: %s %s", index, action.verdict if action.valid else "invalid",
                     action.reason or action.error)
            if action.accepted or last:
                break
            if not action.primitives:
                if action.valid:  # nothing to change: the next critique would see the same robot
                    break
                continue  # invalid: no action this round, the solution stands
            new_pos, new_rot = apply_primitives(working.wrist_pos, working.wrist_rot,
                                                action.primitives, blend)
            working = working.with_wrists(new_pos, new_rot)  # hand-point targets move along
            solution = solve(robot, working, cfg_rounds, init=solution)
            solved_here = True
        chosen = _chosen_round(rounds, cfg_critic)
        for i, r in enumerate(rounds):  # only the result's control-rate array is kept
            if i != chosen % len(rounds):
                r.q_control = None
        final = rounds[chosen]
        final.q_kinematic = final.q_control
        # the exported array: the chosen round's, with the torque and ZMP retiming (once), from the
        # kinematic array its solve made (every re-solve's; round 0's when the caller says so)
        known = final.q_kinematic is not None and (ik_kinematic or final.index in resolved)
        final.q_control, clear, final.source_time = exported_control(
            robot, final.q, targets.fps, cfg_ik, kinematic=final.q_kinematic if known else None)
        final.metrics.update(control_counts(robot, final.q_control, cfg_ik.control_rate_hz, clear))
        export: dict[str, Any] = {}
        if final.accepted:  # the critic's acceptance must hold for the array a user receives
            q = _at_frames(final.q_control, final.source_time, targets.num_frames, targets.fps)
            pos, rot = robot_wrists(robot, q)
            metrics = wrist_metrics(ref_pos, ref_rot, pos, rot, targets.arm_length)
            location_offset, fidelity = judge(q) if judge is not None else (None, {})
            metrics.update(fidelity)
            export = {"metrics": metrics, "renders": {}}
            action, context = critique(final.index, q, pos, rot, location_offset, fidelity,
                                       export["renders"], "export")
            export.update(action=action.to_json(), exchange=context.record)
            log.info("export of round %d: %s %s", final.index, action.verdict if action.valid else "invalid",
                     action.reason or action.error)
        if out is not None:
            comp = renders.comparison(final.q)
            final.renders["final_sheet"] = _store_png(comp.sheet_png("final"), out, "sheet.png")
            from embody.render.compare import render_preview

            preview = render_preview(renders.renderer, cfg_render, motion, body, fit, final.q,
                                     out / "preview")
            if preview is not None:
                from embody.critic.vlm import sha256

                final.renders["preview"] = {"sha256": sha256(preview.read_bytes()),
                                            "path": preview.name}
    finally:
        renders.close()
    return RefineResult(rounds, list(robot.joint_names), keyframes, cfg_critic.kind, chosen, export)


def _at_frames(q_control: np.ndarray, source_time: np.ndarray, num_frames: int, fps: float) -> np.ndarray:
    """The control-rate array (S,n) read at `num_frames` source frames' times (i / fps), its
    samples placed at their own source times (`source_time`, s: k / rate unless the export was
    retimed): linear between its samples, the last sample held past its end (the control grid
    stops at or before the last frame). What the critic judges of an exported array."""
    q_control = np.asarray(q_control, dtype=np.float64)
    if len(q_control) < 2:
        return np.repeat(q_control[:1], num_frames, axis=0)
    st = np.asarray(source_time, dtype=np.float64)
    s = np.interp(np.arange(num_frames) / fps, st, np.arange(len(q_control), dtype=np.float64))
    i = np.minimum(np.floor(s).astype(np.int64), len(q_control) - 2)
    a = (s - i)[:, None]
    return (1.0 - a) * q_control[i] + a * q_control[i + 1]


def _with_reason_primitives(action: Action, context: CritiqueContext, cfg: CriticConfig) -> Action:
    """A rejection that proposes nothing (a VLM's "revise" without primitives) gets the
    geometric critic's primitives for the same round, measured against the same human: a
    rejected sequence is always refined. Returned unchanged when those are empty too (the
    offsets are under every threshold: the next round would critique the same robot)."""
    from embody.critic.geometric import GeometricCritic

    measured = GeometricCritic(cfg).critique(context)
    if not measured.primitives:
        return action
    reason = (f"{action.reason} [no primitive proposed; the geometric critic's: "
              f"{measured.reason}]").strip()
    return dataclasses.replace(action, primitives=measured.primitives, reason=reason)


def _chosen_round(rounds: list[RoundRecord], cfg: CriticConfig) -> int:
    """The result round per `critic.keep` (see CriticConfig); ties go to the earlier round.

    `best` picks among the rounds the critic accepted when it accepted any (so a sequence
    reported accepted exports an accepted round), else among all."""
    keep = cfg.keep if cfg.keep != "auto" else ("best" if cfg.kind == "geometric" else "last")
    if keep == "last":
        return len(rounds) - 1
    key = "fidelity_score" if all("fidelity_score" in r.metrics for r in rounds) else "wrist_mm_mean"
    pool = [i for i, r in enumerate(rounds) if r.accepted] or list(range(len(rounds)))
    return min(pool, key=lambda i: (rounds[i].metrics[key], i))


class _HumanJudge:
    """The human as the critic's reference: landmark-relative palm offsets and fidelity per round."""

    def __init__(self, motion, body, robot, targets, cfg: CriticConfig, cfg_ik) -> None:
        from embody.metrics.embodiments import human_track

        self.robot, self.fps = robot, targets.fps
        self.human = human_track(motion, body, with_contacts=False)
        self.hands: dict[str, dict] = {}
        #: (T,2) frames whose offset toward the face or chest was dropped (`embody.critic.reach`)
        self.blocked: np.ndarray | None = None
        self.reach, self.slack = None, cfg.reach_slack_m
        if cfg.reachable:
            from embody.critic.reach import Reach

            self.reach = Reach(robot)
            # the clearance the IK keeps per frame, hand and surface (face, chest): the collision
            # margin, or more where the human's hand is apart from that surface (`Targets.hand_gap`,
            # columns `hand_clearance.CHANNELS`: hands, left/right chest, left/right face)
            margin = float(cfg_ik.collision_margin)
            gap = np.zeros((targets.num_frames, 5)) if targets.hand_gap is None else np.asarray(targets.hand_gap)
            self.required = np.full((targets.num_frames, 2, 2), margin)
            self.required[:, :, 1] = np.maximum(gap[:, 1:3], margin)
            if gap.shape[1] >= 5:
                self.required[:, :, 0] = np.maximum(gap[:, 3:5], margin)

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
        from embody.metrics.embodiments import robot_track
        from embody.metrics.fidelity import LOCATION_LANDMARKS, compare, nearest_landmark, relative_location

        robot = robot_track(self.robot, q, self.fps, with_contacts=False)
        frames, m = compare(self.human, robot)
        names = [n for n in LOCATION_LANDMARKS if self.human.has(n) and robot.has(n)]
        self.hands = {}  # per hand, for the VLM prompt
        for s, side in enumerate(("left", "right")):
            counts = np.bincount(frames["location_landmark"][:, s], minlength=len(names))
            err = float(frames["location_err"][:, s].mean())
            self.hands[side] = {"landmark": names[int(counts.argmax())], "share": float(counts.max() / len(q)),
                                "location_err": err, "location_cm": err * robot.scale * 100.0,
                                "palm_deg": float(frames["palm_deg"][:, s].mean()),
                                "yaw_deg": _yaw_to_human(self.human, robot, side),
                                "turn_deg": _turn_to_human(self.human, robot, side).tolist()}
        hips = [i for i, n in enumerate(names) if n.endswith("_hip")]
        offset = np.zeros((len(q), 2, 3))
        toward = np.zeros((len(q), 2, 3))  # robot palm → the robot's landmark of the human's nearest
        for s, side in enumerate(("left", "right")):
            k, d = nearest_landmark(self.human, side, names)
            diff = relative_location(self.human, side, names, k) - relative_location(robot, side, names, k)
            move = np.einsum("tab,tb->ta", robot.torso, diff) * robot.scale  # robot torso frame, m
            near = (d < 0.5) & ~np.isin(k, hips)  # a sign's place; not a hand resting by the thigh
            offset[:, s] = np.where(near[:, None], move, 0.0)
            toward[:, s] = np.take_along_axis(robot.points[:, [robot.names.index(n) for n in names]],
                                              k[:, None, None], 1)[:, 0] - robot.point(f"{side}_palm")
        if self.reach is not None:
            toward /= np.maximum(np.linalg.norm(toward, axis=-1, keepdims=True), 1e-9)
            offset, self.blocked = self.reach.clamp(q, offset, self.required, self.slack, toward)
        fidelity = {"location_err": m["location_err"], "location_err_mm": m["location_err_mm"],
                    "palm_deg": m["palm_deg"], "handshape_err": m["handshape_err"],
                    "fidelity_score": m["location_err"] + m["palm_deg"] / 180.0}
        return offset, fidelity


def _yaw_to_human(human, robot, side: str) -> float:
    """The turn about the torso's up axis (deg, + = about +z) that best brings the robot hand's
    palm normal and pointing direction (each in its own torso frame) onto the human's: the
    least-squares yaw of their horizontal parts over the sequence. The IK target's rotation is no
    reference here: on the wristless H1 its yaw disagrees with the human palm, and turns that
    cancelled it raised the palm error round after round (default run, 2026-11-26)."""
    s = ("left", "right").index(side)
    tip = f"{side}_middle_tip" if human.has(f"{side}_middle_tip") and robot.has(f"{side}_middle_tip") \
        else f"{side}_palm"
    pairs = [(human.local(human.normals[:, s]), robot.local(robot.normals[:, s]))]
    pairs += [tuple(t.local(t.point(tip) - t.point(f"{side}_wrist")) for t in (human, robot))]
    cross = dot = 0.0
    for h, r in pairs:
        h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
        r = r / np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-12)
        cross += float((r[:, 0] * h[:, 1] - r[:, 1] * h[:, 0]).sum())
        dot += float((r[:, 0] * h[:, 0] + r[:, 1] * h[:, 1]).sum())
    return float(np.degrees(np.arctan2(cross, dot)))


def _turn_to_human(human, robot, side: str) -> np.ndarray:
    """The rotation (rotation vector in the robot torso frame, degrees: x roll, y pitch, z yaw
    components) that best brings the robot hand's palm normal and pointing direction onto the
    human's, each in its own torso frame: the least-squares (Kabsch) rotation over the sequence.
    Turning the wrist target by it (`critic.primitives`, R' = R_axis · R) addresses a palm
    error whatever its axis; the yaw alone (`_yaw_to_human`) cannot fix a tilted palm."""
    from scipy.spatial.transform import Rotation

    s = ("left", "right").index(side)
    tip = f"{side}_middle_tip" if human.has(f"{side}_middle_tip") and robot.has(f"{side}_middle_tip") \
        else f"{side}_palm"
    pairs = [(human.local(human.normals[:, s]), robot.local(robot.normals[:, s]))]
    pairs += [tuple(t.local(t.point(tip) - t.point(f"{side}_wrist")) for t in (human, robot))]
    h = np.concatenate([p[0] for p in pairs])
    r = np.concatenate([p[1] for p in pairs])
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    r = r / np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-12)
    u, _, vt = np.linalg.svd(r.T @ h)  # R = V diag(1, 1, det) Uᵀ maps r onto h
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return np.degrees(Rotation.from_matrix(rot).as_rotvec())


_TABLE_METRICS = ("wrist_mm_mean", "wrist_mm_p95", "wrist_deg_mean", "wrist_deg_p95",
                  "wrist_dtw_mm", "wrist_offset_arm")


def refine_table(results: Sequence[RefineResult] | Mapping[str, RefineResult]) -> pd.DataFrame:
    """"IK-only vs refined": mean metrics over sequences, plus acceptance and rounds used."""
    items = list(results.values()) if isinstance(results, Mapping) else list(results)
    rows = {}
    for label, pick in (("IK-only", lambda r: r.ik_only), ("refined", lambda r: r.final)):
        refined = label == "refined"
        row = {m: float(np.mean([pick(r).metrics[m] for r in items])) for m in _TABLE_METRICS}
        row["accepted"] = float(np.mean([bool(r.accepted if refined else r.ik_only.accepted)
                                         for r in items]))
        # critique rounds run (the result may be an earlier round, see `critic.keep`)
        row["rounds"] = float(np.mean([len(r.rounds) - 1 if refined else 0 for r in items]))
        row["n"] = len(items)
        rows[label] = row
    return pd.DataFrame.from_dict(rows, orient="index")
