"""AMASS-style npz: the field's SMPL-X (165) and SMPL+H (156) files, BEAT2, and embody's own files.

AMASS is z-up with absolute hands (MoSh++ fits; zero is a flat hand). BEAT2 SMPL-X files
(co-speech mocap as SynTalker/EMAGE release them) carry AMASS's `mocap_frame_rate` key but are
detected by `model` = `smplx2020`: they are y-up, and their hands are mean-relative, because
EMAGE's loaders build the body with `smplx.create(..., use_pca=False)` and leave
`flat_hand_mean` at smplx's default False. Files written by `save` carry an `embody_meta` JSON
entry saying they are already y-up, so re-loading never rotates twice. Every file here records
its frame rate.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError
from embody.io.conventions import Overrides, Setting, normalise
from embody.io.fields import betas10, field, read_npz, scalar, text
from embody.io.npzfile import npz_bytes, write_atomic
from embody.motion import NUM_JOINTS, Motion, MotionSource

META_KEY = "embody_meta"
FRAME_RATE_KEYS = ("mocap_frame_rate", "mocap_framerate")
#: SMPL+H hands sit at 66:111 (left) and 111:156 (right); SMPL-X puts them after jaw and eyes.
SMPLH_BODY = slice(0, 66)
SMPLH_HANDS = slice(66, 156)
SMPLX_HANDS = slice(75, 165)
#: BEAT2's SMPL-X model tag (`model` key).
BEAT2_MODEL = "smplx2020"


def is_beat2(data: dict[str, Any]) -> bool:
    return text(data, "model", "").lower().startswith(BEAT2_MODEL)


def is_amass(data: dict[str, Any]) -> bool:
    return META_KEY in data or any(k in data for k in FRAME_RATE_KEYS)


def smplh_to_smplx(poses: np.ndarray) -> np.ndarray:
    """(T,156) SMPL+H → (T,165) SMPL-X: body and hands copied, jaw and eyes zero."""
    out = np.zeros((poses.shape[0], 165), dtype=poses.dtype)
    out[:, SMPLH_BODY] = poses[:, SMPLH_BODY]
    out[:, SMPLX_HANDS] = poses[:, SMPLH_HANDS]
    return out


def read(path: Path, data: dict[str, Any] | None = None,
         overrides: Overrides | None = None) -> Motion:
    data = read_npz(path) if data is None else data
    meta_json = data.get(META_KEY)
    if "poses" not in data:
        raise InputError(path, "poses", "missing")
    width = np.asarray(data["poses"]).shape[-1] if np.asarray(data["poses"]).ndim == 2 else None
    if width == 156 and meta_json is None:
        poses, fmt = smplh_to_smplx(field(data, "poses", path, width=156)), "amass-smplh"
    else:
        poses, fmt = field(data, "poses", path, width=165), "amass-smplx"
    t = poses.shape[0]
    transl = field(data, "trans", path, rows=t, width=3) if "trans" in data else np.zeros((t, 3))
    fps_key = next((k for k in FRAME_RATE_KEYS if k in data), None)
    fps = scalar(data, FRAME_RATE_KEYS, path, default=0.0)
    if fps == 0.0 and (overrides is None or overrides.fps is None):
        raise InputError(path, "mocap_frame_rate", "missing")
    fps_setting = Setting(fps, f"data: {fps_key}")
    meta: dict[str, Any] = {}
    if meta_json is not None:
        try:
            info = json.loads(text(data, META_KEY, "{}", path))
        except json.JSONDecodeError as exc:
            raise InputError(path, META_KEY, f"not valid JSON: {exc.msg}") from None
        if not isinstance(info, dict) or not isinstance(info.get("meta", {}), dict):
            raise InputError(path, META_KEY, "expected a JSON object with an object 'meta'")
        if info.get("up_axis", "y") != "y" or info.get("hand_convention", "absolute") != "absolute":
            raise InputError(path, META_KEY, "embody files must be y-up with absolute hands")
        meta, fmt = check_meta(info.get("meta", {}), path), "embody"
        up = Setting("y", f"data: {META_KEY}")
        hands = Setting("absolute", f"data: {META_KEY}")
    elif is_beat2(data):
        fmt = "beat2"
        up = Setting("y", f"detected: BEAT2 layout (model={BEAT2_MODEL}) is y-up")
        hands = Setting("relative", "detected: BEAT2 layout; EMAGE's loaders use flat_hand_mean=False")
    else:
        up = Setting("z", f"default: AMASS layout ({fps_key}) is z-up")
        hands = Setting("absolute", "default: AMASS (MoSh++) hands are absolute")
    pose, transl, fps, hand_convention, provenance = normalise(
        poses.reshape(t, NUM_JOINTS, 3), transl, fps=fps_setting, up_axis=up, hands=hands,
        overrides=overrides)
    return Motion(pose=pose, transl=transl, betas=betas10(data, "betas", path), fps=fps,
                  gender=text(data, "gender", "neutral", path),
                  source=MotionSource(str(path), fmt, hand_convention, provenance),  # type: ignore[arg-type]
                  meta=meta)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _str_list(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)


def _artifact_list(value: Any) -> bool:
    return isinstance(value, list) and all(
        isinstance(a, dict) and isinstance(a.get("kind"), str) and _is_int(a.get("start"))
        and _is_int(a.get("end")) for a in value)


def _sign_list(value: Any) -> bool:
    return isinstance(value, list) and all(
        isinstance(s, dict) and isinstance(s.get("gloss", ""), str)
        and _is_int(s.get("start", 0)) and _is_int(s.get("end", 0)) for s in value)


#: The `meta` keys embody reads (inspect, the dataset, the critic's prompt, synth's tables),
#: each with its check and what it must be; other keys are carried along unread.
_META_FIELDS: dict[str, tuple[Any, str]] = {
    "id": (lambda v: isinstance(v, str), "a string"),
    "text": (lambda v: isinstance(v, str), "a string"),
    "gloss": (_str_list, "a list of strings"),
    "artifacts": (_artifact_list, "a list of objects with a string 'kind' and integer "
                                  "'start' and 'end'"),
    "signs": (_sign_list, "a list of objects with a string 'gloss' and integer 'start' and 'end'"),
    "seed": (_is_int, "an integer"),
    "index": (_is_int, "an integer"),
    "generator": (lambda v: isinstance(v, str), "a string"),
}


def check_meta(meta: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """The `meta` of an `embody_meta` with the keys embody reads type-checked: InputError
    naming `embody_meta.meta.<key>` (exit 2), not a traceback wherever the value is used."""
    for key, (ok, what) in _META_FIELDS.items():
        if key in meta and not ok(meta[key]):
            raise InputError(path, f"{META_KEY}.meta.{key}",
                             f"must be {what}, got {type(meta[key]).__name__}")
    return dict(meta)


def _numpy_json(value: Any) -> Any:
    """Numpy scalars and arrays in `meta` (stages often put them there) as plain JSON."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def save(motion: Motion, path: str | Path) -> Path:
    """Write `motion` as an AMASS-style SMPL-X npz (y-up, absolute hands), atomically.

    The bytes depend only on the motion, so the same motion always gives the same file.
    """
    path = Path(path)
    info = {"format_version": 1, "up_axis": "y", "hand_convention": "absolute",
            "source": {"path": motion.source.path, "format": motion.source.format,
                       "hand_convention": motion.source.hand_convention},
            "meta": motion.meta}
    try:
        meta_json = json.dumps(info, sort_keys=True, separators=(",", ":"), default=_numpy_json)
    except TypeError as exc:
        raise InputError(path, "meta", f"not JSON-serialisable: {exc}") from None
    arrays = {
        "poses": motion.pose165().astype(np.float32),
        "trans": motion.transl.astype(np.float32),
        "betas": motion.betas.astype(np.float32),
        "gender": np.array(motion.gender),
        "mocap_frame_rate": np.array(motion.fps, dtype=np.float64),
        META_KEY: np.array(meta_json),
    }
    write_atomic(path, npz_bytes(arrays))
    return path
