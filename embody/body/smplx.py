"""A user's SMPL-X model (`SMPLX_*.npz`/`.pkl`) through the `body-models` package, in torch.

SMPL-X files are licensed and never shipped: this backend exists for users who have one. The file
is validated up front so a wrong file fails with its path and the offending key, not deep in
`body-models`.
"""

from __future__ import annotations

import copy
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch
from body_models._common.chumpy_fix import load_model_dict
from body_models.smplx.torch import SMPLX

from embody.body.base import BodyModel, ConvexPiece
from embody.body.convex import part_hulls
from embody.body.parts import dominant_parts
from embody.config.body import BodyConfig
from embody.errors import ConfigError, InputError
from embody.motion import JOINT_NAMES, NUM_JOINTS, PARENTS

#: body-models reads shape coefficients from shapedirs[..., :300] and expressions after them.
_SHAPE_BASIS = 300
_EXPRESSIONS = 10
#: Required keys and their number of dimensions (None: any object).
_REQUIRED = {"v_template": 2, "f": 2, "weights": 2, "shapedirs": 3, "posedirs": 3,
             "J_regressor": 2, "kintree_table": 2, "hands_meanl": 1, "hands_meanr": 1,
             "joint2num": None}


def _read(path: Path) -> dict[str, Any]:
    """Load and check the arrays body-models needs; every failure is an `InputError`."""
    if path.is_dir():
        raise InputError(path, None, "is a folder; expected an SMPL-X .npz or .pkl file")
    if not path.is_file():
        raise InputError(path, None, "SMPL-X model file not found (set body.model_path to your "
                                     "SMPLX_NEUTRAL.npz)")
    if path.suffix not in (".npz", ".pkl"):
        raise InputError(path, None, f"expected an SMPL-X .npz or .pkl file, got {path.suffix!r}")
    try:
        data = load_model_dict(path)
    except Exception as exc:  # zip, pickle and OS errors all mean "unreadable"
        raise InputError(path, None, f"cannot read SMPL-X model: {exc}") from None
    for key, ndim in _REQUIRED.items():
        if key not in data:
            raise InputError(path, key, "missing; this is not an SMPL-X model file")
        if ndim is not None and np.ndim(data[key]) != ndim:
            raise InputError(path, key, f"expected {ndim} dimensions, got shape {np.shape(data[key])}")
    num_vertices = np.shape(data["v_template"])[0]
    expected = {"v_template": (num_vertices, 3), "weights": (num_vertices, NUM_JOINTS),
                "J_regressor": (NUM_JOINTS, num_vertices), "kintree_table": (2, NUM_JOINTS),
                "hands_meanl": (45,), "hands_meanr": (45,)}
    for key, shape in expected.items():
        if np.shape(data[key]) != shape:
            raise InputError(path, key, f"expected shape {shape}, got {np.shape(data[key])}")
    if np.shape(data["shapedirs"])[:2] != (num_vertices, 3) or \
            np.shape(data["shapedirs"])[2] <= _SHAPE_BASIS:
        raise InputError(path, "shapedirs", f"expected ({num_vertices}, 3, >{_SHAPE_BASIS}) "
                                            f"(shape + expression), got {np.shape(data['shapedirs'])}")
    parents = np.asarray(data["kintree_table"][0], dtype=np.int64)
    if not np.array_equal(parents[1:], PARENTS[1:]):
        raise InputError(path, "kintree_table", "kinematic tree is not SMPL-X's")
    return data


class SMPLXBody(BodyModel):
    """SMPL-X (55 joints, flat hand mean), with pose correctives, via `body-models`."""

    name = "smplx"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).expanduser()
        data = _read(self.path)
        try:
            model = SMPLX(model_path=self.path, flat_hand_mean=True)
        except Exception as exc:
            raise InputError(self.path, None, f"body-models cannot load it: {exc}") from None
        self._expressions = min(_EXPRESSIONS, np.shape(data["shapedirs"])[2] - _SHAPE_BASIS)
        self.joint_names = JOINT_NAMES
        self.parents = PARENTS.copy()
        self.faces = np.asarray(data["f"], dtype=np.int64)
        self.skin_weights = np.asarray(data["weights"], dtype=np.float32)
        self.hand_mean = np.concatenate([np.asarray(data["hands_meanl"], dtype=np.float32),
                                         np.asarray(data["hands_meanr"], dtype=np.float32)]).reshape(30, 3)
        parts = dominant_parts(self.skin_weights, self.joint_names)
        self.part_names, self.part_joints, self.vertex_parts = parts.names, parts.joints, parts.vertex_parts
        self._lock = threading.Lock()
        self._models: dict[tuple[torch.dtype, torch.device], SMPLX] = {
            (torch.float32, torch.device("cpu")): model}
        self._hulls: dict[bytes, list[ConvexPiece]] = {}

    @classmethod
    def from_config(cls, cfg: BodyConfig) -> "SMPLXBody":
        """`model_path` is a file, or a folder holding `SMPLX_{GENDER}.npz`."""
        if cfg.model_path is None:
            raise ConfigError("body.model_path", "required when body.backend is 'smplx' "
                                                 "(path to SMPLX_NEUTRAL.npz)")
        path = Path(cfg.model_path).expanduser()
        if path.is_dir():
            path = path / f"SMPLX_{cfg.gender.upper()}.npz"
        return cls(path)

    def _model(self, like: torch.Tensor) -> SMPLX:
        key = (like.dtype, like.device)
        with self._lock:
            if key not in self._models:
                base = self._models[(torch.float32, torch.device("cpu"))]
                self._models[key] = copy.deepcopy(base).to(dtype=like.dtype, device=like.device)
            return self._models[key]

    def _params(self, pose: torch.Tensor, betas: torch.Tensor,
                transl: torch.Tensor | None) -> dict[str, torch.Tensor]:
        if pose.ndim != 3 or pose.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"pose must be (T, {NUM_JOINTS}, 3), got {tuple(pose.shape)}")
        t = pose.shape[0]
        betas = betas.to(pose)
        params = {"body_pose": pose[:, 1:22], "head_pose": pose[:, 22:25], "hand_pose": pose[:, 25:],
                  "pelvis_rotation": pose[:, 0],
                  "shape": betas.reshape(-1, betas.shape[-1]).expand(t, -1),
                  "expression": pose.new_zeros(t, self._expressions)}
        if transl is not None:
            params["global_translation"] = transl.to(pose)
        return params

    def joint_transforms(self, pose: torch.Tensor, betas: torch.Tensor,
                         transl: torch.Tensor | None = None) -> torch.Tensor:
        return self._model(pose).forward_skeleton(**self._params(pose, betas, transl))

    def joints(self, pose: torch.Tensor, betas: torch.Tensor,
               transl: torch.Tensor | None = None) -> torch.Tensor:
        return self.joint_transforms(pose, betas, transl)[..., :3, 3]

    def vertices(self, pose: torch.Tensor, betas: torch.Tensor,
                 transl: torch.Tensor | None = None) -> torch.Tensor:
        return self._model(pose).forward_vertices(**self._params(pose, betas, transl))

    def rest_vertices(self, betas: torch.Tensor) -> torch.Tensor:
        rest = betas.new_zeros(1, NUM_JOINTS, 3)
        return self.vertices(rest, betas.reshape(-1, betas.shape[-1])[:1])[0]

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """Shaped rest joint positions (J,3), differentiable in betas."""
        rest = betas.new_zeros(1, NUM_JOINTS, 3)
        return self.joints(rest, betas.reshape(-1, betas.shape[-1])[:1])[0]

    def collision_geometry(self, betas: np.ndarray) -> list[ConvexPiece]:
        b = torch.as_tensor(np.asarray(betas, dtype=np.float64).reshape(-1))
        key = b.numpy().astype(np.float32).tobytes()
        with self._lock:
            cached = self._hulls.get(key)
        if cached is None:
            with torch.no_grad():
                rest = self.rest_vertices(b).numpy()
                bind = self.rest_joints(b).numpy()
            cached = part_hulls(rest, bind, self.part_joints, self.vertex_parts)
            with self._lock:
                self._hulls[key] = cached
        return cached
