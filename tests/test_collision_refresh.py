"""The optimiser's frame-by-frame refresh (`collision.refresh`): the displacement bound holds,
kept rows select what fresh rows select, merged rows are in frame order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.collision.energy import _blend, contacts, penetrations
from embody.collision.refresh import Refresh, _merge, displacement, part_reaches
from collision_cases import body, model  # noqa: F401 (fixtures)
from test_collision_compiled import crossing_poses

MARGIN, REACH = 0.022, 0.001


def _tr(body, pose: np.ndarray) -> torch.Tensor:
    return body.joint_transforms(torch.as_tensor(pose, dtype=torch.float32),
                                 torch.zeros(10, dtype=torch.float32))


def _points_in_parts(model, tr: torch.Tensor) -> torch.Tensor:
    """Every model point (T,H,S,3) in every part's joint frame: (T,C,H,S,3)."""
    d = model.tensors(torch.float64, torch.device("cpu"))
    tr = tr.double()
    blend = _blend(d, tr)                                                   # (T,J,3,4)
    a = blend[:, d["chunk_joints"]]                                         # (T,H,U,3,4)
    m = (d["chunk_weights"][None, ..., None, None] * a[:, :, None]).sum(3)   # (T,H,S,3,4)
    p = (m[..., :3] @ d["chunk_points"][None, ..., None]).squeeze(-1) + m[..., 3]
    g = tr[:, d["part_joints"]]                                             # (T,C,4,4)
    x = p[:, None] - g[:, :, None, None, :3, 3]
    return torch.einsum("tcab,tchsa->tchsb", g[..., :3, :3], x)


def test_displacement_bounds_every_point_in_every_part_frame(body, model):
    rng = np.random.default_rng(1)
    pose = crossing_poses()
    mask = torch.as_tensor(model.chunk_mask)
    reach = torch.as_tensor(part_reaches(model, MARGIN))[None, :, None, None]
    for scale in (1e-3, 1e-2, 0.1):
        moved = pose + rng.normal(0.0, scale, pose.shape)
        a, b = _tr(body, pose), _tr(body, moved)
        bound = displacement(model, MARGIN, a, b)
        qa, qb = _points_in_parts(model, a), _points_in_parts(model, b)
        near = (qa.norm(dim=-1) <= reach) & mask
        step = torch.where(near, (qb - qa).norm(dim=-1), 0.0).flatten(1).amax(1)
        assert (step > 0).all()
        assert (step <= bound).all(), (step, bound)
        assert (bound < 20 * step + 1e-5).all()  # a bound, not a blanket refresh


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(torch.equal(getattr(a, f), getattr(b, f)) for f in ("t", "h", "n", "b", "plane", "f"))


def test_kept_rows_select_what_fresh_rows_select(body, model):
    """Small moves keep the rows (no refresh), large ones refresh the frames that moved;
    either way the narrow phase selects the same points, planes and values as rows found at
    the pose itself."""
    rng = np.random.default_rng(2)
    pose = crossing_poses()
    refresh = Refresh(model, MARGIN, REACH, None)
    refresh(_tr(body, pose))
    assert refresh.refreshed == len(pose)
    small = pose + rng.normal(0.0, 2e-4, pose.shape)
    rows = refresh(_tr(body, small))
    assert refresh.refreshed == len(pose)  # nothing moved by half the margin
    big = small.copy()
    big[3] += rng.normal(0.0, 0.05, big[3].shape)
    rows_big = refresh(_tr(body, big))
    assert len(pose) < refresh.refreshed < 2 * len(pose)
    for p, near in ((small, rows), (big, rows_big)):
        tr = _tr(body, p)
        sel = penetrations(model, tr, -0.001, near)
        assert sel is not None and len(sel.t) > 0
        assert _same(sel, penetrations(model, tr, -0.001, contacts(model, tr, MARGIN)))


def test_merge_keeps_frame_order_and_each_sides_order():
    old = np.array([[0, 1], [0, 2], [1, 5], [2, 7], [2, 8], [4, 1]], dtype=np.int64)
    fresh = np.array([[1, 9], [1, 3], [3, 4]], dtype=np.int64)
    redo = np.array([False, True, False, True, False])
    out = _merge(old, fresh, redo)
    assert out.tolist() == [[0, 1], [0, 2], [1, 9], [1, 3], [2, 7], [2, 8], [3, 4], [4, 1]]


def test_displacement_over_the_moving_joints_is_the_whole_bound(body, model):
    """When only a subtree of joints moves, `_displacement_at` over those joints gives the
    whole `displacement` bound, value for value (what `Refresh(joints=...)` uses)."""
    from embody.body.compiled_fk import subtree
    from embody.collision.refresh import _displacement_at, joint_levers
    rng = np.random.default_rng(2)
    pose = crossing_poses()
    moved = pose.copy()
    moved[:, 16:22] += rng.normal(0.0, 0.05, (len(pose), 6, 3))  # elbows, wrists, hands
    a, b = _tr(body, pose), _tr(body, moved)
    src, _, _, parents, order = body.compiled_fk_inputs(torch.zeros(1, 55, 3), torch.zeros(10))
    joints = subtree(parents, order, np.flatnonzero(np.isin(src, np.arange(16, 22))))
    same = np.setdiff1d(np.arange(a.shape[1]), joints)
    assert torch.equal(a[:, same], b[:, same])
    fast = _displacement_at(a.numpy(), b.numpy(), joints, joint_levers(model),
                            model.part_joints, part_reaches(model, MARGIN))
    assert np.array_equal(fast, displacement(model, MARGIN, a, b).numpy())
