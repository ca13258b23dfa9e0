"""Energy against an independent ground truth: exact intersection volumes of the posed pieces
(manifold3d), part tightness (overfill) and clearance of the skinned mesh (python-fcl)."""

from __future__ import annotations

import itertools

import fcl
import manifold3d as m3
import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from embody.body import MannequinBody
from embody.collision import collision_model, frame_energies, overfill_report, part_volumes
from embody.collision.exclusions import checked_pairs, part_groups
from embody.motion import JOINT_NAMES
from embody.synth import generate_sequence

J = JOINT_NAMES.index
ARMS = [J(n) for n in ("left_collar", "right_collar", "left_shoulder", "right_shoulder",
                       "left_elbow", "right_elbow", "left_wrist", "right_wrist")]


@pytest.fixture(scope="module")
def body() -> MannequinBody:
    return MannequinBody()


def validation_poses() -> np.ndarray:
    """30 frames of two synthetic signing sequences and 30 random arm/hand poses."""
    synth = [generate_sequence(0, i).pose[::12] for i in (0, 4)]
    rng = np.random.default_rng(7)
    rand = np.zeros((30, 55, 3))
    rand[:, ARMS] = rng.normal(0, 0.6, (30, len(ARMS), 3))
    rand[:, 25:55] = rng.normal(0, 0.3, (30, 30, 3))
    rand[:, J("left_shoulder"), 2] -= 0.9
    rand[:, J("right_shoulder"), 2] += 0.9
    return np.concatenate([*synth, rand])[:60].astype(np.float64)


def intersection_volumes(body, pose: np.ndarray) -> np.ndarray:
    """Σ over checked part pairs of the exact volume of posed piece ∩ posed piece (m³)."""
    vols = part_volumes(body)
    groups, part_group = part_groups(vols.part_names)
    checked = checked_pairs(groups, body.joint_names, body.parents)
    g = body.joint_transforms(torch.as_tensor(pose), torch.zeros(10, dtype=torch.float64)).numpy()
    out = np.zeros(len(pose))
    for t in range(len(pose)):
        world = [pc.vertices @ g[t, pc.joint, :3, :3].T + g[t, pc.joint, :3, 3]
                 for pc in vols.pieces]
        lo = np.array([w.min(0) for w in world])
        hi = np.array([w.max(0) for w in world])
        for i, k in itertools.combinations(range(len(world)), 2):
            a, b = vols.pieces[i].part, vols.pieces[k].part
            if not checked[part_group[a], part_group[b]]:
                continue
            if (lo[i] >= hi[k]).any() or (lo[k] >= hi[i]).any():
                continue
            both = m3.Manifold.hull_points(world[i]) ^ m3.Manifold.hull_points(world[k])
            out[t] += both.volume()
    return out


def test_energy_agrees_with_exact_intersection_volume(body):
    pose = validation_poses()
    assert len(pose) >= 50
    model = collision_model(body, vertex_stride=1)
    energy = frame_energies(model, body.joint_transforms(
        torch.as_tensor(pose), torch.zeros(10, dtype=torch.float64))).numpy()
    volume = intersection_volumes(body, pose)
    assert (volume == 0).sum() >= 5 and (volume > 1e-6).sum() >= 10
    assert np.all(energy[volume == 0] == 0.0)
    assert np.all(energy[volume > 1e-6] > 0.0)
    rho = spearmanr(energy, volume).statistic
    assert rho >= 0.9, rho


def test_parts_are_tight(body):
    report = overfill_report(body)
    assert len(report) == len(part_volumes(body).part_names)
    assert (report["overfill_pct"] <= 10.0).all(), report.sort_values("overfill_pct").tail()
    assert (report["pieces"] >= 1).all() and report["pieces"].max() > 1  # some were split


def test_cached_volumes_are_identical_after_reload(body, monkeypatch):
    from embody.collision import volumes

    first = part_volumes(body)
    monkeypatch.setattr(volumes, "_memory", {})
    again = part_volumes(body)  # from the disk cache
    assert again is not first and again.key == first.key
    for a, b in zip(first.pieces, again.pieces):
        assert a.part == b.part and np.array_equal(a.planes, b.planes)


def _mesh_parts(body, pose: np.ndarray):
    """fcl BVH models of the skinned mesh's parts (faces whose three vertices share a part)."""
    verts = body.vertices(torch.as_tensor(pose[None]), torch.zeros(10, dtype=torch.float64))[0]
    verts = verts.numpy()
    vols = part_volumes(body)
    fp = vols.vertex_parts[body.faces]
    out = {}
    for p in range(len(vols.part_names)):
        faces = body.faces[(fp == p).all(1)]
        m = fcl.BVHModel()
        m.beginModel(len(verts), len(faces))
        m.addSubModel(verts, faces)
        m.endModel()
        out[p] = fcl.CollisionObject(m, fcl.Transform())
    return out


def test_clear_pose_scores_zero(body):
    """Arms forward and apart, fingers spread: every checked pair of the skinned mesh stays
    ≥ 2 cm apart, and the energy of its skinned vertices is exactly 0 (so is the T-pose's)."""
    pose = np.zeros((1, 55, 3))
    pose[0, J("left_shoulder")] = (0.0, 0.5, -0.6)
    pose[0, J("right_shoulder")] = (0.0, -0.5, 0.6)
    pose[0, J("left_elbow"), 1], pose[0, J("right_elbow"), 1] = -0.6, 0.6
    model = collision_model(body, vertex_stride=1)
    parts = _mesh_parts(body, pose[0])
    checked = model.checked
    hand = {model.groups.index("left_hand"), model.groups.index("right_hand")}
    closest = np.inf
    for a, b in itertools.combinations(parts, 2):
        ga, gb = model.part_group[a], model.part_group[b]
        if not checked[a, b] or ga in hand and ga == gb:
            continue
        res = fcl.DistanceResult()
        closest = min(closest, fcl.distance(parts[a], parts[b], fcl.DistanceRequest(), res))
    assert closest >= 0.02, closest
    both = np.concatenate([pose, np.zeros((1, 55, 3))])  # and the rest/T-pose
    e = frame_energies(model, body.joint_transforms(torch.as_tensor(both),
                                                    torch.zeros(10, dtype=torch.float64)))
    assert e.tolist() == [0.0, 0.0]


def test_volumes_asked_again_for_a_shape_are_the_first_answer(body, monkeypatch):
    """The per-body (betas, max_overfill) → key memo answers what the full key would: the
    same volumes for the same shape, and after the in-memory volumes are dropped the disk
    cache is read again."""
    from embody.collision import volumes

    betas = np.zeros(10)
    first = part_volumes(body, betas)
    assert part_volumes(body, betas.copy()) is first and part_volumes(body) is first
    rest = body.rest_vertices(torch.as_tensor(betas)).double().numpy()
    assert first.key == volumes._mesh_key(body, rest, volumes.rest_frames(body, betas), 0.10)
    assert volumes._keys[body][(betas.tobytes(), 0.10)] == first.key
    monkeypatch.setattr(volumes, "_memory", {})
    again = part_volumes(body, betas)
    assert again is not first and again.key == first.key
