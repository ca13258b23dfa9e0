"""Which configuration keys a user sets, what each means, and which are internal tuning.

`embody config --explain` prints this. Every key of `Config` is one or the other: `USER_KEYS`
names the keys a user is expected to set (one line each, with its unit); every other key is
internal tuning, chosen by measurement (docs/performance.md), and listed with the first line of
its comment in `embody/config/<section>.py`. A test checks that every user key exists.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap
from typing import Any

from pydantic import BaseModel

from embody.config import Config

#: Keys a user sets: dotted key -> one-line meaning, with its unit.
USER_KEYS: dict[str, str] = {
    # run: what to run and where
    "run.store": "artifact store directory (path)",
    "run.name": "run name; default derived from dataset, split and robot (text)",
    "run.workers": "parallel workers (count)",
    "run.runner": "threads, processes or dask (choice)",
    "run.dask_address": "Dask scheduler to run on, e.g. tcp://host:8786; null: a local cluster (address)",
    "run.batch_size": "sequences per task submission; raise it for datasets of thousands (count)",
    "run.max_task_runs": "most task runs per Prefect flow run; more run as subflows of this size (count)",
    "run.limit": "process only the first N sequences; null: all (count)",
    "run.offset": "skip the first N sequences, to split a dataset between drivers (count)",
    "run.critic": "run the critic refinement step (on/off)",
    "run.render": "render comparison sheets and previews (on/off)",
    "run.report": "build the report at the end of the run (on/off)",
    "run.seed": "seed of the synthetic dataset (integer)",
    "run.synth_n": "sequences in the synthetic dataset (count)",
    # inputs
    "io.fps": "frame rate of every input; null: from the file or its dataset's default (Hz)",
    "io.up_axis": "up axis of the input: y, z or camera; null: detected (choice)",
    "io.hands": "hand convention of the input: absolute or relative; null: detected (choice)",
    "io.max_frames": "longest sequence accepted (frames)",
    "io.allow_outside_paths": "let manifests and split files point outside the dataset folder (on/off)",
    # body and robot
    "body.backend": "body model: mannequin (bundled) or smplx (your licensed file) (choice)",
    "body.model_path": "SMPL-X .npz/.pkl file or folder, for backend smplx (path)",
    "body.gender": "which SMPLX_{GENDER}.npz to use from a folder (choice)",
    "robot.name": "robot definition configs/robots/<name>.yaml (name)",
    "robot.mjcf_path": "another MJCF file with the same kinematic tree (path)",
    "robot.robots_dir": "folder of robot definitions; null: configs/robots (path)",
    # collision mitigation
    "collision.enabled": "mitigate self-collisions before retargeting (on/off)",
    "collision.mask": "joints the optimiser may move: a preset (arms, hands, ...) or joints (choice)",
    "collision.joints": "joint names moved when mask is joints (list)",
    "collision.steps": "most optimiser steps per window (count)",
    "collision.lambda_col": "weight of the collision energy L_col (Eq. 1) (weight)",
    "collision.lambda_close": "weight of staying close to the input pose (weight)",
    "collision.lambda_smooth": "weight of temporal smoothness (weight)",
    "collision.allow_pairs": "body-part pairs allowed to touch, e.g. [[right_hand, head]] (list of name pairs)",
    "collision.depth_metrics": "measure mesh penetration depth before and after (on/off)",
    "collision.device": "cpu, cuda or auto for the optimiser; cuda results are not bit-reproducible (choice)",
    "collision.window_frames": "longer sequences are mitigated in windows of this length; bounds memory (frames)",
    # retargeting
    "ik.location_preserving": "anchor hands to the robot's own face and body landmarks, not the plain wrist (on/off)",
    "ik.w_wrist_pos": "weight of wrist position tracking (weight)",
    "ik.w_wrist_rot": "weight of wrist orientation tracking (weight)",
    "ik.w_elbow_pos": "weight of elbow position tracking (weight)",
    "ik.w_smooth": "weight of joint acceleration smoothness (weight)",
    "ik.w_jerk": "weight of joint jerk smoothness (weight)",
    "ik.w_collision": "weight of the robot self-collision proxies (weight)",
    "ik.collision_margin": "clearance the self-collision proxies keep (m)",
    "ik.kinematics": "FK backend: pytorch_kinematics or tree (same results to 1e-9 m) (choice)",
    "ik.iterations": "most Levenberg-Marquardt iterations of the main solve (count)",
    "ik.hands": "retarget the fingers (on/off)",
    "ik.enforce_velocity_limits": "keep joint velocities within the robot's limits (on/off)",
    "ik.contact_repair": "repair MuJoCo self-contacts at every control-rate sample of the export (on/off)",
    "ik.control_rate_hz": "rate of the exported trajectory (Hz)",
    "ik.polish_iterations": "extra iterations on MuJoCo's exact contacts; 0 off, ~1.5x solve time (count)",
    "ik.window_frames": "longer sequences are solved in windows of this length; bounds memory (frames)",
    # critic
    "critic.kind": "geometric (offline) or vlm (an OpenAI-compatible endpoint) (choice)",
    "critic.rounds": "critique rounds after the IK-only solution (count)",
    "critic.keep": "which round is the result: auto, best or last (choice)",
    "critic.accept_location": "accept when each hand's location error is below this (body scales: shoulder widths)",
    "critic.accept_palm_deg": "accept when each palm normal is within this of the human's (degrees)",
    "critic.vlm.base_url": "OpenAI-compatible endpoint (URL)",
    "critic.vlm.model": "model name the endpoint serves (text)",
    "critic.vlm.api_key_env": "environment variable holding the API key; the key is never config (name)",
    "critic.vlm.api_key_required": "fail without a key; false sends no Authorization header (on/off)",
    "critic.vlm.timeout_s": "timeout of one request (s)",
    "critic.vlm.max_retries": "retries of a failed request (count)",
    "critic.vlm.request_budget": "most requests one run may send, retries included (count)",
    "critic.vlm.temperature": "sampling temperature (unitless)",
    "critic.vlm.max_tokens": "longest answer (tokens)",
    "critic.vlm.prompt_path": "prompt file; null: configs/critic/prompt.md (path)",
    "critic.vlm.send_keyframes": "send each keyframe pair as its own image besides the sheet (on/off)",
    # rendering
    "render.width": "width of one sheet image (px)",
    "render.height": "height of one sheet image (px)",
    "render.keyframes": "keyframes per sequence in the sheet (count)",
    "render.views": "cameras: front, side (list)",
    "render.gl": "OpenGL backend: egl or osmesa (choice)",
    "render.preview_format": "animated preview: mp4, gif, webp or none (choice)",
    "render.preview_fps": "preview frame rate, plays in real time; null: the source rate (Hz)",
    "render.preview_max_frames": "most frames drawn for a preview (frames)",
    # fidelity metrics
    "fidelity.location_radius": "a hand is at a landmark within this distance (body scales)",
    "fidelity.contact_eps": "human surfaces closer than this are in contact (m)",
    "fidelity.baseline": "also solve the plain IK for Table III's IK-only row (on/off)",
}


#: Tuning keys declared without a comment of their own (a group's second key, say): their line.
TUNING_NOTES: dict[str, str] = {
    "io.max_fps": "highest accepted frame rate (Hz); see io.min_fps",
    "collision.lr": "Adam's step size (rad)",
    "collision.lr_floor": "smallest step size the decay reaches, as a fraction of lr",
    "collision.lambda_max": "cap of the λ_col continuation",
    "collision.pull_back_depth": "deepest mesh penetration the pull-back leaves (m)",
    "collision.pull_back_iterations": "search steps of the pull-back's scale per frame (count)",
    "collision.pull_back_window_s": "the pull-back's scale is smoothed over this window (s)",
    "collision.early_stop_rtol": "read by no code today (a candidate for removal)",
    "collision.early_stop_patience": "read by no code today (a candidate for removal)",
    "collision.early_stop_stall": "refreshes the optimiser continues after every frame is clear (count)",
    "collision.refresh_margin": "broad-phase margin of the optimiser's candidate pairs (m)",
    "collision.window_overlap": "frames shared (cross-faded) by consecutive collision windows",
    "ik.shape_iterations": "Adam iterations of the shape fit (count)",
    "ik.shape_lr": "Adam step size of the shape fit",
    "ik.w_head_rot": "weight of head orientation tracking (0: off)",
    "ik.ramp_iterations": "cold-start iterations at ramp_collision (count)",
    "ik.polish_pad": "frames around a near pair the polish also checks (frames)",
    "ik.contact_iterations": "LM iterations per contact round (count)",
    "ik.contact_pad": "frames around a contact the contact phase also moves (frames)",
    "ik.w_contact": "weight of MuJoCo's contact rows in the contact phase",
    "ik.contact_stall_mm": "improvement of the deepest contact below which a round stalls (mm)",
    "ik.window_overlap": "frames shared (cross-faded) by consecutive IK windows",
    "render.camera_distance": "free-camera distance; null: automatic framing (m)",
    "render.camera_elevation": "camera elevation (degrees)",
    "render.background_rgb": "background colour (RGB 0..1)",
    "critic.angle_step_deg": "default angle of a primitive that names none (degrees)",
    "critic.max_angle_deg": "largest angle one primitive may carry (degrees)",
    "critic.accept_yaw_deg": "geometric critic's yaw acceptance (degrees)",
    "critic.reach_slack_m": "slack subtracted from the reachable room (m)",
    "critic.angle_quantum_deg": "geometric critic's angle quantum (degrees)",
    "critic.window_factor": "a window is used when its offset exceeds the sequence's by this factor",
    "critic.vlm.backoff_s": "first retry delay, doubled per retry (s)",
    "critic.vlm.max_backoff_s": "longest retry delay (s)",
}


def config_keys(model: BaseModel | None = None, prefix: str = "") -> list[str]:
    """Every dotted leaf key of the configuration, in model order."""
    model = Config() if model is None else model
    keys: list[str] = []
    for name in type(model).model_fields:
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            keys += config_keys(value, f"{prefix}{name}.")
        else:
            keys.append(f"{prefix}{name}")
    return keys


@functools.cache
def _comments(cls: type) -> dict[str, str]:
    """Field name -> the first sentence of its own `#:` comment (or its `description`)."""
    lines = textwrap.dedent(inspect.getsource(cls)).splitlines()
    out: dict[str, str] = {}
    for node in ast.parse("\n".join(lines)).body[0].body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        text, i = [], node.lineno - 2
        while i >= 0 and lines[i].strip().startswith("#:"):
            text.insert(0, lines[i].strip()[2:].strip())
            i -= 1
        field = cls.model_fields.get(node.target.id)
        line = " ".join(text) or (field.description if field and field.description else "")
        line = line.split(". ")[0].rstrip(".")
        if line:
            out[node.target.id] = line if len(line) <= 120 else line[:119] + "…"
    return out


def describe(key: str, cfg: Config | None = None) -> str:
    """The one line `--explain` prints for `key`: the user meaning, else the source comment."""
    if key in USER_KEYS:
        return USER_KEYS[key]
    if key in TUNING_NOTES:
        return TUNING_NOTES[key]
    model: Any = Config() if cfg is None else cfg
    *path, name = key.split(".")
    for part in path:
        model = getattr(model, part)
    return _comments(type(model)).get(name) or f"see embody/config/{path[0]}.py"


def explain(cfg: Config) -> str:
    """Two lists: the keys a user sets (value, meaning, unit), then the internal tuning keys."""
    keys = config_keys(cfg)
    flat = {k: _value(cfg, k) for k in keys}
    user = [k for k in keys if k in USER_KEYS]
    tuning = [k for k in keys if k not in USER_KEYS]
    width = max(len(k) for k in keys)
    out = [f"# Keys you set ({len(user)}): --set section.key=value or --config FILE", ""]
    out += [f"{k:<{width}}  {flat[k]!s:<22}  {describe(k, cfg)}" for k in user]
    out += ["", f"# Internal tuning ({len(tuning)}): chosen by measurement (docs/performance.md); "
            "change only to experiment", ""]
    out += [f"{k:<{width}}  {flat[k]!s:<22}  {describe(k, cfg)}" for k in tuning]
    return "\n".join(out) + "\n"


def _value(cfg: Config, key: str) -> Any:
    value: Any = cfg
    for part in key.split("."):
        value = getattr(value, part)
    return value
