"""Batched forward kinematics and linear blend skinning in torch (shared by both backends)."""

from __future__ import annotations

import numpy as np
import torch

#: Frames skinned at once; bounds the (T,V,3,4) blended-transform buffer.
SKIN_CHUNK = 64


def tree_levels(parents: np.ndarray) -> list[np.ndarray]:
    """Joints grouped by depth (root excluded), so FK runs one batched step per level."""
    depth = np.zeros(len(parents), dtype=np.int64)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [np.flatnonzero(depth == d) for d in range(1, int(depth.max()) + 1)]


def offsets_from_joints(rest_joints: torch.Tensor, parents: np.ndarray) -> torch.Tensor:
    """Parent-relative bone offsets (..., J, 3); the root keeps its absolute position."""
    parent_pos = rest_joints[..., np.maximum(parents, 0), :]
    root = torch.zeros_like(rest_joints[..., :1, :])
    mask = torch.cat((root, torch.ones_like(rest_joints[..., 1:, :])), dim=-2)
    return rest_joints - parent_pos * mask


def forward_kinematics(local_rot: torch.Tensor, offsets: torch.Tensor, root: torch.Tensor,
                       parents: np.ndarray, levels: list[np.ndarray]) -> torch.Tensor:
    """World transforms (T,J,4,4) from local rotations (T,J,3,3), bone offsets ((T,)J,3)
    and the root's world position (T,3). Joints carry no rest rotation."""
    t, j = local_rot.shape[:2]
    offsets = offsets.expand(t, j, 3)
    rot = local_rot
    pos = torch.cat((root[:, None, :], torch.zeros_like(offsets[:, 1:])), dim=1)
    for level in levels:
        idx = torch.as_tensor(level, device=local_rot.device)
        par = torch.as_tensor(parents[level], device=local_rot.device)
        parent_rot = rot[:, par]
        rot = rot.index_copy(1, idx, parent_rot @ local_rot[:, idx])
        step = (parent_rot @ offsets[:, idx, :, None])[..., 0]
        pos = pos.index_copy(1, idx, pos[:, par] + step)
    bottom = torch.zeros(t, j, 1, 4, dtype=rot.dtype, device=rot.device)
    bottom[..., 3] = 1.0
    return torch.cat((torch.cat((rot, pos[..., None]), dim=-1), bottom), dim=-2)


def skin(transforms: torch.Tensor, rest_vertices: torch.Tensor, bind_positions: torch.Tensor,
         weights: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning: v = Σ_j w_vj (R_j (v_rest − b_j) + t_j) for (T,J,4,4) transforms,
    rest mesh (V,3), bind joint positions (J,3) and dense weights (V,J) → (T,V,3)."""
    rot = transforms[..., :3, :3]
    trans = transforms[..., :3, 3] - (rot @ bind_positions[..., None])[..., 0]
    bone = torch.cat((rot, trans[..., None]), dim=-1).flatten(-2)  # (T,J,12)
    out = []
    x, y, z = (rest_vertices[:, None, i] for i in range(3))
    for start in range(0, bone.shape[0], SKIN_CHUNK):
        m = torch.matmul(weights, bone[start:start + SKIN_CHUNK]).unflatten(-1, (3, 4))
        # column by column: ~3x faster on CPU than a product-and-sum over (T,V,3,3); summed
        # in place in the same order (((m0·x + m1·y) + m2·z) + m3), so the same bits
        v = m[..., 0] * x
        v += m[..., 1] * y
        v += m[..., 2] * z
        v += m[..., 3]
        out.append(v)
    return torch.cat(out, dim=0)
