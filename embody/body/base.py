"""The body-model protocol every stage relies on (torch, differentiable, batched over frames).

Inputs are always SMPL-X ordered: `pose` (T,55,3) axis-angle with absolute (flat-mean) hands,
`betas` (10,), optional `transl` (T,3). Outputs are y-up metres.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class ConvexPiece:
    """One convex volume of a body part, expressed in the part's joint-local frame.

    `planes` are (F,4) rows (n, d) with unit outward normals n, so that the signed distance of a
    local point p to the piece is max_f(n_f·p + d_f) (exact inside, a lower bound outside).
    """

    part: int
    joint: int
    vertices: np.ndarray
    planes: np.ndarray


class BodyModel(ABC):
    """A skinned SMPL-X-driven body: joints, vertices, parts and convex collision geometry."""

    #: Backend name, used in cache keys ("mannequin", "smplx").
    name: str
    #: Joint names of this model's skeleton (SMPL-X names where they exist).
    joint_names: tuple[str, ...]
    #: Parent index per joint (-1 for the root).
    parents: np.ndarray
    #: Triangle faces (F,3) of the skinned mesh.
    faces: np.ndarray
    #: Part names; part i is driven by joint `part_joints[i]`.
    part_names: tuple[str, ...]
    part_joints: np.ndarray
    #: Dominant-skinning-weight part of each vertex (V,).
    vertex_parts: np.ndarray
    #: Skinning weights (V,J).
    skin_weights: np.ndarray
    #: SMPL-X relaxed hand mean (30,3): left 15 then right 15, axis-angle.
    hand_mean: np.ndarray

    def joint_index(self, name: str) -> int:
        """Index of a joint by SMPL-X name (`embody.motion.JOINT_NAMES`), whatever the backend."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise ValueError(f"{self.name} body has no joint {name!r}; "
                             f"known: {', '.join(self.joint_names)}") from None

    def joint_indices(self, names: Iterable[str]) -> np.ndarray:
        """Indices (K,) of several joints, e.g. to slice `joints(...)[:, idx]`."""
        return np.array([self.joint_index(n) for n in names], dtype=np.int64)

    @abstractmethod
    def joint_transforms(self, pose: torch.Tensor, betas: torch.Tensor,
                         transl: torch.Tensor | None = None) -> torch.Tensor:
        """World transforms (T,J,4,4) of every joint."""

    def joint_transforms_compiled(self, pose: torch.Tensor, betas: torch.Tensor) -> torch.Tensor:
        """`joint_transforms` for an optimiser's inner loop, differentiable in `pose` only:
        bodies with a compiled FK (`compiled_fk`) use it on the CPU, equal to rounding;
        by default it is `joint_transforms`."""
        return self.joint_transforms(pose, betas)

    def compiled_fk_inputs(self, pose: torch.Tensor, betas: torch.Tensor
                           ) -> tuple[np.ndarray, ...] | None:
        """What `joint_transforms_compiled` hands the compiled FK for poses like `pose`
        (T,55,3): (source (K,) pose rows of the K joints (55 = a zero row), offsets, root,
        parents, order; float64 arrays), so that a caller can run `compiled_fk`'s kernels
        and their backward directly; None for bodies without a compiled FK."""
        return None

    @abstractmethod
    def joints(self, pose: torch.Tensor, betas: torch.Tensor,
               transl: torch.Tensor | None = None) -> torch.Tensor:
        """Joint positions (T,J,3)."""

    @abstractmethod
    def vertices(self, pose: torch.Tensor, betas: torch.Tensor,
                 transl: torch.Tensor | None = None) -> torch.Tensor:
        """Skinned mesh vertices (T,V,3)."""

    def vertices_array(self, pose: torch.Tensor, betas: torch.Tensor) -> np.ndarray:
        """`vertices` (T,V,3) as a NumPy array, without autograd (the mesh judge): the same
        values; a body may answer faster."""
        with torch.no_grad():
            return self.vertices(pose, betas).cpu().numpy()

    @abstractmethod
    def rest_vertices(self, betas: torch.Tensor) -> torch.Tensor:
        """Shaped mesh in the zero pose (V,3)."""

    @abstractmethod
    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """Shaped joint positions in the zero pose (J,3), differentiable in betas (shape fit)."""

    @abstractmethod
    def collision_geometry(self, betas: np.ndarray) -> list[ConvexPiece]:
        """Per-part convex pieces for this shape, in joint-local frames."""

    def tpose(self, num_frames: int = 1) -> torch.Tensor:
        """The canonical T-pose (all-zero axis-angle, absolute hands): (T,55,3)."""
        return torch.zeros(num_frames, 55, 3)
