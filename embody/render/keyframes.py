"""Keyframes at motion extrema: where the wrists hold still or reach furthest out.

Uniform sampling misses the moments a sign is defined by (holds, extreme hand positions) and
wastes columns on transitions; a critic looking at a few images needs those moments.
"""

from __future__ import annotations

import numpy as np


def select_keyframes(wrist_pos: np.ndarray, k: int, *, smooth: int = 2) -> np.ndarray:
    """Sorted indices of up to `k` keyframes of wrist trajectories (T,2,3).

    Candidates are the first/last frame, local minima of wrist speed and local extrema of each
    wrist coordinate. They are ranked by how far both wrists are from their mean position plus
    how still they are, then picked greedily at least T/(2k) frames apart; uniform frames fill in
    when too few candidates exist. Pure NumPy, so the choice is deterministic.
    """
    pos = np.asarray(wrist_pos, dtype=np.float64).reshape(len(wrist_pos), -1)
    num_frames = len(pos)
    k = int(min(k, num_frames))
    if smooth > 0 and num_frames > 2 * smooth + 1:
        kernel = np.ones(2 * smooth + 1) / (2 * smooth + 1)
        padded = np.pad(pos, ((smooth, smooth), (0, 0)), mode="edge")
        pos = np.stack([np.convolve(padded[:, c], kernel, mode="valid") for c in range(pos.shape[1])], 1)
    speed = np.zeros(num_frames)
    speed[1:] = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    speed[0] = speed[1] if num_frames > 1 else 0.0
    candidates = {0, num_frames - 1}
    interior = np.arange(1, num_frames - 1)
    if len(interior):
        s_prev, s, s_next = speed[interior - 1], speed[interior], speed[interior + 1]
        candidates.update(interior[(s <= s_prev) & (s < s_next)].tolist())
        for c in range(pos.shape[1]):
            x_prev, x, x_next = pos[interior - 1, c], pos[interior, c], pos[interior + 1, c]
            peaks = ((x >= x_prev) & (x > x_next)) | ((x <= x_prev) & (x < x_next))
            candidates.update(interior[peaks].tolist())
    spread = np.linalg.norm(pos - pos.mean(axis=0), axis=1)
    score = spread / (spread.max() + 1e-9) + (1.0 - speed / (speed.max() + 1e-9))
    order = sorted(candidates, key=lambda i: (-score[i], i))
    gap = max(1, num_frames // (2 * k))
    chosen: list[int] = []
    for i in order:
        if len(chosen) == k:
            break
        if all(abs(i - j) >= gap for j in chosen):
            chosen.append(i)
    for i in np.linspace(0, num_frames - 1, k).round().astype(int):
        if len(chosen) == k:
            break
        if int(i) not in chosen:
            chosen.append(int(i))
    for i in range(num_frames):  # only when rounding collided above
        if len(chosen) == k:
            break
        if i not in chosen:
            chosen.append(i)
    return np.array(sorted(chosen), dtype=np.int64)
