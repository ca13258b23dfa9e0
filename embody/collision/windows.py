"""Collision mitigation of long sequences in overlapping windows, so memory follows the window.

The optimiser differentiates through every frame at once; at 20,000 frames that alone took the
process past 20 GB. Frames interact only through the smoothness term (a second difference), so
windows of `window_frames` with `window_overlap` shared frames, cross-faded linearly over the
overlap, give the same kind of result with memory bounded by the window. Only the masked
joints are blended: the rest stay the input bit for bit. Sequences no longer than one window
go straight to `mitigate`.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from embody.body.base import BodyModel
from embody.collision.metrics import sequence_metrics
from embody.collision.optimize import (CollisionResult, frame_collision_energies, judge,
                                       mitigate)
from embody.config.collision import CollisionConfig
from embody.motion import Motion


def windows(frames: int, size: int, overlap: int) -> list[tuple[int, int]]:
    """[start, end) spans covering `frames`, each ≤ `size`, consecutive ones sharing `overlap`
    frames; a short tail is merged into the previous span (every span has ≥ 2 frames)."""
    if frames <= size:
        return [(0, frames)]
    step = size - overlap
    spans = [(s, min(s + size, frames)) for s in range(0, frames - overlap, step)]
    if len(spans) > 1 and spans[-1][1] - spans[-1][0] <= overlap + 1:
        spans[-2:] = [(spans[-2][0], frames)]
    return spans


def _part(motion: Motion, start: int, end: int) -> Motion:
    return replace(motion, pose=motion.pose[start:end], transl=motion.transl[start:end],
                   meta=dict(motion.meta))


def mitigate_windowed(motion: Motion, body: BodyModel,
                      cfg: CollisionConfig | None = None) -> CollisionResult:
    """`mitigate` per window of `cfg.window_frames`, cross-faded over `cfg.window_overlap`."""
    cfg = cfg or CollisionConfig()
    spans = windows(motion.num_frames, cfg.window_frames, cfg.window_overlap)
    if len(spans) == 1:
        return mitigate(motion, body, cfg)
    start_time = time.perf_counter()
    judging = cfg.depth_metrics  # judged once on the blended whole, not per window
    cfg = cfg.model_copy(update={"depth_metrics": False})
    x0 = motion.pose
    pose = x0.copy()
    before = np.zeros(motion.num_frames)
    after = np.zeros(motion.num_frames)
    steps, idx, prev_end = 0, None, 0
    for start, end in spans:
        res = mitigate(_part(motion, start, end), body, cfg)
        idx = res.mask
        steps += int(res.metrics.get("steps", 0))
        before[start:end] = res.frame_energy_before
        new = res.motion.pose
        shared = max(0, prev_end - start)  # frames also covered by the previous window
        if shared:
            w = ((np.arange(shared) + 1) / (shared + 1))[:, None, None].astype(np.float32)
            old = pose[start:start + shared][:, idx]
            pose[start:start + shared, idx] = (1 - w) * old + w * new[:shared][:, idx]
        pose[start + shared:end, idx] = new[shared:][:, idx]
        after[start + shared:end] = res.frame_energy_after[shared:]
        if shared:  # the cross-faded frames are new poses: score them
            blended = _part(motion.with_pose(pose), start, start + max(shared, 2))
            after[start:start + shared] = frame_collision_energies(blended, body, cfg)[:shared]
        prev_end = end
    fixed = motion.with_pose(pose)
    if after.mean() > before.mean():  # never hand back something worse than the input
        fixed, after = motion.with_pose(x0), before.copy()
    fixed, after, judged, depth_s = judge(body, motion, fixed, after, idx, cfg, judging)
    metrics = sequence_metrics(x0, fixed.pose, float(before.mean()), float(after.mean()),
                               time.perf_counter() - start_time - depth_s, steps)
    metrics.update(mask=cfg.mask, windows=len(spans), **judged)
    return CollisionResult(fixed, metrics, before, after,
                           np.asarray(idx if idx is not None else [], dtype=np.int64))
