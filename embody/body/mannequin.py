"""The default body: mannequin-x's wooden mannequin, posed and skinned in torch.

Shape-dependent geometry (the reshaped rest mesh) comes from mannequin-x's own NumPy reshape,
cached per betas; everything pose-dependent is torch and differentiable. Joints are also
differentiable in betas (rest joints are linear in them), which the shape fit needs.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import torch
from mannequin import Mannequin
from mannequin import _io as mannequin_io

from embody.body.base import BodyModel, ConvexPiece
from embody.body.convex import part_hulls
from embody.body.compiled_fk import compiled_fk
from embody.body.kinematics import forward_kinematics, offsets_from_joints, skin, tree_levels
from embody.body.parts import dominant_parts
from embody.body.rotations import axis_angle_to_matrix
from embody.motion import JOINT_NAMES, NUM_BETAS, NUM_JOINTS

#: Mannequin joint j takes its rotation from SMPL-X joint SMPLX_SOURCE[j]; 55 means "none"
#: (the zero-length L_Hand/R_Hand joints). Jaw and eyes have no mannequin joint.
SMPLX_SOURCE = np.array([*range(22), NUM_JOINTS, NUM_JOINTS, *range(25, 55)], dtype=np.int64)
MANNEQUIN_JOINT_NAMES = (*JOINT_NAMES[:22], "left_hand", "right_hand", *JOINT_NAMES[25:])
#: Shaped rest meshes kept per betas (each ≈0.6 MB).
_CACHE_SIZE = 32


def _betas_key(betas: torch.Tensor | np.ndarray) -> bytes:
    """One shape per call: (10,) or rows that are all equal, as float32 bytes."""
    b = betas.detach().cpu().numpy() if isinstance(betas, torch.Tensor) else np.asarray(betas)
    rows = b.reshape(-1, NUM_BETAS).astype(np.float32)
    if not np.all(rows == rows[0]):
        raise ValueError("per-frame betas differ; the mesh needs one shape per call")
    return rows[0].tobytes()


class MannequinBody(BodyModel):
    """mannequin-x `wooden` (24,256 vertices, 54 joints) with `flat_hand_mean=True` semantics."""

    name = "mannequin"

    def __init__(self) -> None:
        self._model = Mannequin("wooden", flat_hand_mean=True)
        calibration = mannequin_io.load_calibration()
        self.joint_names = MANNEQUIN_JOINT_NAMES
        self.parents = np.asarray(self._model.parents, dtype=np.int64)
        self.faces = np.asarray(self._model.faces, dtype=np.int64)
        self.hand_mean = calibration.hand_mean.astype(np.float32)
        self._joint_rest = calibration.joint_rest
        self._joint_dirs = calibration.joint_dirs
        self._levels = tree_levels(self.parents)
        # mannequin-x's bound skin: 4 strongest influences, rigid shells on one joint
        idx, w = self._model._skin_joint_indices, self._model._skin_weights
        weights = np.zeros((idx.shape[0], len(self.parents)), dtype=np.float32)
        np.add.at(weights, (np.arange(idx.shape[0])[:, None], idx), w)
        self.skin_weights = weights
        parts = dominant_parts(weights, self.joint_names)
        self.part_names, self.part_joints, self.vertex_parts = parts.names, parts.joints, parts.vertex_parts
        self._lock = threading.Lock()
        self._shapes: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._hulls: OrderedDict[bytes, list[ConvexPiece]] = OrderedDict()
        self._constants: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, ...]] = {}
        #: The skin weights' nonzeros for `vertices_array` (`sparse_skin.sparse_weights`).
        self._sparse: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # -- shape --------------------------------------------------------------------------------
    def _shaped(self, key: bytes) -> tuple[np.ndarray, np.ndarray]:
        """(rest vertices (V,3), bind joint positions (J,3)) for one betas, via mannequin-x."""
        with self._lock:
            if key not in self._shapes:
                self._model.reshape(np.frombuffer(key, dtype=np.float32))
                identity = self._model._identity
                self._shapes[key] = (identity["skin_vertices"].copy(),
                                     identity["skin_bind_positions"].copy())
                if len(self._shapes) > _CACHE_SIZE:
                    self._shapes.popitem(last=False)
            self._shapes.move_to_end(key)
            return self._shapes[key]

    def _tensors(self, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
        key = (dtype, device)
        if key not in self._constants:
            self._constants[key] = tuple(
                torch.as_tensor(a, dtype=dtype, device=device)
                for a in (self._joint_rest, self._joint_dirs, self.skin_weights))
        return self._constants[key]

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """Shaped rest joint positions ((T,)J,3), linear and differentiable in betas."""
        joint_rest, joint_dirs, _ = self._tensors(betas.dtype, betas.device)
        if betas.shape[-1] != NUM_BETAS:
            raise ValueError(f"betas must end in {NUM_BETAS}, got {tuple(betas.shape)}")
        return joint_rest + torch.einsum("jdk,...k->...jd", joint_dirs, betas)

    def rest_vertices(self, betas: torch.Tensor) -> torch.Tensor:
        vertices, _ = self._shaped(_betas_key(betas))
        return torch.as_tensor(vertices, dtype=betas.dtype, device=betas.device)

    # -- pose ---------------------------------------------------------------------------------
    def joint_transforms(self, pose: torch.Tensor, betas: torch.Tensor,
                         transl: torch.Tensor | None = None, *, compiled: bool = False
                         ) -> torch.Tensor:
        """World transforms (T,J,4,4); `compiled`: FK by `compiled_fk` (CPU, differentiable in
        `pose` only)."""
        if pose.ndim != 3 or pose.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"pose must be (T, {NUM_JOINTS}, 3), got {tuple(pose.shape)}")
        betas = betas.to(dtype=pose.dtype, device=pose.device)
        rest = self.rest_joints(betas.reshape(-1, NUM_BETAS) if betas.ndim > 1 else betas)
        padded = torch.cat((pose, torch.zeros_like(pose[:, :1])), dim=1)
        axis_angle = padded[:, torch.as_tensor(SMPLX_SOURCE, device=pose.device)]
        root = rest[..., 0, :].expand(pose.shape[0], 3)
        if transl is not None:
            root = root + transl.to(dtype=pose.dtype, device=pose.device)
        offsets = offsets_from_joints(rest, self.parents)
        if compiled:
            return compiled_fk(axis_angle, offsets, root, self.parents, self._levels)
        return forward_kinematics(axis_angle_to_matrix(axis_angle), offsets, root, self.parents,
                                  self._levels)

    def compiled_fk_inputs(self, pose: torch.Tensor, betas: torch.Tensor
                           ) -> tuple[np.ndarray, ...] | None:
        if pose.device.type != "cpu" or betas.requires_grad:
            return None
        with torch.no_grad():
            betas = betas.to(dtype=pose.dtype)
            rest = self.rest_joints(betas.reshape(-1, NUM_BETAS) if betas.ndim > 1 else betas)
            root = rest[..., 0, :].expand(pose.shape[0], 3).contiguous()
            offsets = offsets_from_joints(rest, self.parents)
        order = np.concatenate([np.flatnonzero(np.asarray(self.parents) < 0),
                                *self._levels]).astype(np.int64)
        return (SMPLX_SOURCE, offsets.double().reshape(-1, *offsets.shape[-2:]).numpy(),
                root.double().numpy(), np.asarray(self.parents, dtype=np.int64), order)

    def joint_transforms_compiled(self, pose: torch.Tensor, betas: torch.Tensor) -> torch.Tensor:
        if pose.device.type != "cpu" or betas.requires_grad:
            return self.joint_transforms(pose, betas)
        return self.joint_transforms(pose, betas, compiled=True)

    def joints(self, pose: torch.Tensor, betas: torch.Tensor,
               transl: torch.Tensor | None = None) -> torch.Tensor:
        return self.joint_transforms(pose, betas, transl)[..., :3, 3]

    def vertices(self, pose: torch.Tensor, betas: torch.Tensor,
                 transl: torch.Tensor | None = None) -> torch.Tensor:
        """Skinned vertices; the rest mesh is a per-betas constant, so betas gradients flow only
        through the skeleton (the skin follows its joints)."""
        transforms = self.joint_transforms(pose, betas, transl)
        rest, bind = (torch.as_tensor(a, dtype=pose.dtype, device=pose.device)
                      for a in self._shaped(_betas_key(betas)))
        _, _, weights = self._tensors(pose.dtype, pose.device)
        return skin(transforms, rest, bind, weights)

    def vertices_array(self, pose: torch.Tensor, betas: torch.Tensor) -> np.ndarray:
        """`vertices` bit for bit as NumPy (`sparse_skin.skin_array`), without autograd."""
        from embody.body.sparse_skin import skin_array, sparse_weights  # numba: on first use
        with torch.no_grad():
            transforms = self.joint_transforms(pose, betas)
            rest, bind = (torch.as_tensor(a, dtype=pose.dtype, device=pose.device)
                          for a in self._shaped(_betas_key(betas)))
            _, _, weights = self._tensors(pose.dtype, pose.device)
            if pose.dtype != torch.float64 or pose.device.type != "cpu":
                return skin(transforms, rest, bind, weights).cpu().numpy()  # `vertices`' path
            if self._sparse is None:
                self._sparse = sparse_weights(weights.cpu().numpy())
            return skin_array(transforms, rest, bind, weights, self._sparse)

    # -- collision ----------------------------------------------------------------------------
    def collision_geometry(self, betas: np.ndarray) -> list[ConvexPiece]:
        key = _betas_key(np.asarray(betas))
        with self._lock:
            cached = self._hulls.get(key)
        if cached is None:
            rest, bind = self._shaped(key)
            cached = part_hulls(rest, bind, self.part_joints, self.vertex_parts)
            with self._lock:
                self._hulls[key] = cached
                if len(self._hulls) > _CACHE_SIZE:
                    self._hulls.popitem(last=False)
        return cached
