"""Part segmentation by dominant skinning weight, and the per-part convex hulls."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.body import MannequinBody
from embody.body.convex import THICKEN, hull_piece
from embody.body.parts import default_merge, dominant_parts
from embody.motion import JOINT_NAMES


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


def test_default_merge():
    assert default_merge("left_index2") == "left_wrist"
    assert default_merge("right_thumb1") == "right_wrist"
    assert default_merge("left_hand") == "left_wrist"
    assert default_merge("jaw") == default_merge("left_eye") == "head"
    assert default_merge("left_elbow") == "left_elbow"
    assert default_merge("pelvis") == "pelvis"


def test_dominant_parts_small_case():
    names = ["pelvis", "left_wrist", "left_index1", "head", "jaw"]
    weights = np.array([[0.9, 0.1, 0, 0, 0],
                        [0.2, 0.3, 0.5, 0, 0],   # finger → wrist
                        [0, 0, 0, 0.4, 0.6],     # jaw → head
                        [0, 0.7, 0.3, 0, 0]])
    parts = dominant_parts(weights, names)
    assert parts.names == ("pelvis", "left_wrist", "head")
    assert parts.joints.tolist() == [0, 1, 3]
    assert parts.vertex_parts.tolist() == [0, 1, 2, 1]
    unmerged = dominant_parts(weights, names, merge=lambda n: n)
    assert unmerged.names == ("pelvis", "left_wrist", "left_index1", "jaw")
    assert unmerged.vertex_parts.tolist() == [0, 2, 3, 1]


def test_mannequin_parts_cover_every_vertex(body):
    v = body.skin_weights.shape[0]
    assert body.vertex_parts.shape == (v,) and body.skin_weights.shape == (v, 54)
    assert np.allclose(body.skin_weights.sum(1), 1.0, atol=1e-5)
    assert set(np.unique(body.vertex_parts)) == set(range(len(body.part_names)))
    owner = [body.joint_names[j] for j in body.skin_weights.argmax(1)]
    expected = np.array([body.joint_index(default_merge(n)) for n in owner])
    np.testing.assert_array_equal(body.part_joints[body.vertex_parts], expected)
    assert [body.joint_names[j] for j in body.part_joints] == list(body.part_names)
    assert {"left_wrist", "right_wrist", "head", "spine3", "left_elbow"} <= set(body.part_names)
    assert not any("index" in n or "thumb" in n for n in body.part_names)


@pytest.mark.parametrize("seed", [None, 0])
def test_hulls_contain_their_part(body, seed):
    betas = np.zeros(10) if seed is None else np.random.default_rng(seed).normal(size=10)
    pieces = body.collision_geometry(betas)
    assert [p.part for p in pieces] == list(range(len(body.part_names)))
    rest = body.rest_vertices(torch.tensor(betas)).numpy()
    bind = body.rest_joints(torch.tensor(betas)).numpy()
    for piece in pieces:
        assert piece.joint == body.part_joints[piece.part]
        n, d = piece.planes[:, :3], piece.planes[:, 3]
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
        local = rest[body.vertex_parts == piece.part] - bind[piece.joint]
        signed = (local @ n.T + d).max(axis=1)
        assert signed.max() <= 1e-5
        # a point well outside (beyond the farthest vertex) is outside
        far = local[np.argmax(np.linalg.norm(local, axis=1))] * 2.0
        assert (n @ far + d).max() > 0
    assert body.collision_geometry(betas) is pieces  # cached per betas


def test_hull_of_posed_rigid_part_follows_its_joint(body):
    """Pieces are joint-local: transforming them by the joint's world transform covers the
    posed part wherever the part is rigid (the head shell)."""
    betas = torch.zeros(10, dtype=torch.float64)
    pose = torch.zeros(1, 55, 3, dtype=torch.float64)
    pose[0, 15] = torch.tensor([0.4, 0.3, -0.2])
    pose[0, 0] = torch.tensor([0.0, 1.0, 0.0])
    head = body.part_names.index("head")
    piece = body.collision_geometry(betas.numpy())[head]
    transform = body.joint_transforms(pose, betas)[0, piece.joint].numpy()
    verts = body.vertices(pose, betas)[0].numpy()
    rigid = (body.vertex_parts == head) & (body.skin_weights[:, piece.joint] > 0.999)
    local = (verts[rigid] - transform[:3, 3]) @ transform[:3, :3]
    assert rigid.sum() > 100
    assert (local @ piece.planes[:, :3].T + piece.planes[:, 3]).max() <= 1e-5


def test_flat_part_is_thickened():
    square = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    piece = hull_piece(3, 7, square)
    assert (piece.part, piece.joint) == (3, 7)
    assert (square @ piece.planes[:, :3].T + piece.planes[:, 3]).max() <= 1e-12
    assert np.isclose(piece.vertices[:, 2].max(), THICKEN)


def test_smplx_joint_names_cover_merge_targets():
    for name in JOINT_NAMES:
        assert default_merge(name) in JOINT_NAMES
