"""Report figures (matplotlib, Agg): collision energies, pose change vs reduction, wrist tracks.

Each function writes one PNG and returns its path; none needs a display.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

_DPI = 120  # labels stay legible at natural size (the page shows them unscaled)
_SIDES = ("left", "right")
_AXES = ("x", "y", "z")


def _save(fig: plt.Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    # `tight_layout` leaves a placeholder layout engine, for which `savefig` draws the whole
    # figure once more before the drawing it saves (ticks, labels, no pixels): ~a third of a
    # plot's CPU for the same bytes. The layout is already applied; no engine, no extra draw.
    fig.set_layout_engine(None)
    # Fixed metadata so seeded runs give identical bytes.
    fig.savefig(path, dpi=_DPI, metadata={"Software": None})
    plt.close(fig)
    return path


def collision_energy(collision: pd.DataFrame, path: Path) -> Path:
    """Grouped bars of collision energy before/after, one pair per sequence (log scale)."""
    ids = [str(i) for i in collision.index]
    x = np.arange(len(ids))
    fig, ax = plt.subplots(figsize=(min(max(6.0, 0.45 * len(ids) + 2), 13.0), 4.0))
    ax.bar(x - 0.2, collision["energy_before"], 0.4, label="before")
    ax.bar(x + 0.2, collision["energy_after"], 0.4, label="after")
    ax.set_xticks(x, ids, rotation=60, ha="right", fontsize=9)
    ax.set_ylabel("collision energy")
    if (collision[["energy_before", "energy_after"]] > 0).all().all():
        ax.set_yscale("log")
    ax.legend()
    ax.set_title("Collision energy per sequence")
    fig.tight_layout()
    return _save(fig, path)


def pose_vs_reduction(collision: pd.DataFrame, path: Path) -> Path:
    """Scatter of pose change (MSE vs original) against collision reduction (%)."""
    fig, ax = plt.subplots(figsize=(7.0, 4.5))
    ax.scatter(collision["reduction_pct"], collision["pose_mse"], s=14)
    for sid, row in collision.iterrows():
        ax.annotate(str(sid), (row["reduction_pct"], row["pose_mse"]), fontsize=8)
    ax.set_xlabel("collision reduction (%)")
    ax.set_ylabel("pose MSE vs. original")
    ax.set_title("Pose change vs. collision reduction")
    fig.tight_layout()
    return _save(fig, path)


def worst_window(error: np.ndarray, width: int) -> slice:
    """The `width`-frame window with the largest mean error (whole range if shorter)."""
    error = np.asarray(error, dtype=np.float64)
    if len(error) <= width:
        return slice(0, len(error))
    sums = np.convolve(error, np.ones(width), mode="valid")
    start = int(np.argmax(sums))
    return slice(start, start + width)


def wrist_tracks(tracks: dict[str, np.ndarray], fps: float, path: Path, *,
                 title: str, window_s: float = 2.0) -> Path:
    """Wrist positions (reference, IK-only, refined …) over the worst window of the IK track.

    `tracks` maps a label to (T,2,3) left/right wrist positions in metres; the first entry is the
    reference and the second the one whose error picks the window.
    """
    labels = list(tracks)
    ref = np.asarray(tracks[labels[0]], dtype=np.float64)
    judged = np.asarray(tracks[labels[min(1, len(labels) - 1)]], dtype=np.float64)
    err = np.linalg.norm(judged - ref, axis=-1).mean(axis=-1)
    win = worst_window(err, max(2, int(round(window_s * fps))))
    t = np.arange(len(ref))[win] / fps
    fig, axes = plt.subplots(2, 3, figsize=(9, 4.2), sharex=True)
    for s, side in enumerate(_SIDES):
        for a, axis in enumerate(_AXES):
            ax = axes[s, a]
            for k, label in enumerate(labels):
                ax.plot(t, np.asarray(tracks[label])[win, s, a], lw=1.2,
                        ls="-" if k == 0 else "--", label=label)
            ax.set_title(f"{side} wrist {axis}", fontsize=8)
            ax.tick_params(labelsize=7)
    axes[1, 0].set_xlabel("time (s)")
    axes[0, 0].set_ylabel("m")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{title}: worst {win.stop - win.start}-frame window", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _runs(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """(start, stop, label) of each run of equal consecutive labels."""
    out, start = [], 0
    for t in range(1, len(labels) + 1):
        if t == len(labels) or labels[t] != labels[start]:
            out.append((start, t, int(labels[start])))
            start = t
    return out


def location_error(err: np.ndarray, landmark: np.ndarray, names: list[str], fps: float,
                   path: Path, *, title: str) -> Path:
    """Location error over time per hand (T,2 body scales), the background of each span coloured
    and labelled by the human hand's nearest landmark (what the error is measured against)."""
    err, landmark = np.asarray(err, dtype=np.float64), np.asarray(landmark, dtype=np.int64)
    t = np.arange(len(err)) / fps
    used = sorted({int(k) for k in np.unique(landmark) if 0 <= k < len(names)})
    cmap = plt.get_cmap("tab20")
    colour = {k: cmap(i % 20) for i, k in enumerate(used)}
    fig, axes = plt.subplots(2, 1, figsize=(10, 4.6), sharex=True)
    top = max(float(np.nanmax(err)) if err.size else 0.0, 1e-3) * 1.25
    min_label = max(1, int(0.08 * len(err)))  # label spans wide enough to read
    for s, side in enumerate(_SIDES):
        ax = axes[s]
        for start, stop, k in _runs(landmark[:, s]):
            if k not in colour:
                continue
            x0, x1 = start / fps, stop / fps
            ax.axvspan(x0, x1, color=colour[k], alpha=0.25, lw=0)
            if stop - start >= min_label:
                ax.text((x0 + x1) / 2, top * 0.97, names[k], ha="center", va="top", fontsize=7)
        ax.plot(t, err[:, s], color="#222", lw=1.2)
        ax.set_ylim(0, top)
        ax.set_ylabel(f"{side} hand\n(body scales)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time (s)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colour[k], alpha=0.4) for k in used]
    fig.legend(handles, [names[k] for k in used], loc="lower center", ncol=min(len(used), 8),
               fontsize=7, frameon=False, title="nearest landmark of the human hand",
               title_fontsize=7)
    fig.suptitle(f"{title}: location error (palm relative to its nearest landmark)", fontsize=9)
    fig.tight_layout(rect=(0, 0.1 if used else 0, 1, 1))
    return _save(fig, path)


def physics_trace(torque_ratio: np.ndarray, palm_err_mm: np.ndarray, fps: float, path: Path, *,
                  title: str, palm_bound_mm: float = 10.0) -> Path:
    """Per sample of the exported array: the worst joint's inverse-dynamics torque over its
    effort limit (1 = the limit) and the worst palm's tracking error in the physics replay (mm),
    with the physics-valid bounds drawn."""
    torque_ratio = np.asarray(torque_ratio, dtype=np.float64)
    palm = np.asarray(palm_err_mm, dtype=np.float64)
    t = np.arange(len(torque_ratio)) / fps
    fig, axes = plt.subplots(2, 1, figsize=(10, 4.2), sharex=True)
    axes[0].plot(t, torque_ratio, color="#222", lw=1.2)
    axes[0].axhline(1.0, color="#c33", lw=1.0, ls="--", label="effort limit")
    axes[0].fill_between(t, 1.0, torque_ratio, where=torque_ratio > 1.0, color="#c33", alpha=0.3)
    axes[0].set_ylabel("|τ| / limit\n(worst joint)", fontsize=8)
    axes[0].legend(fontsize=7, loc="upper right")
    axes[1].plot(t, palm, color="#225", lw=1.2)
    axes[1].axhline(palm_bound_mm, color="#c33", lw=1.0, ls="--", label=f"{palm_bound_mm:g} mm (p95 bound)")
    axes[1].set_ylabel("palm error (mm)\n(worst palm)", fontsize=8)
    axes[1].legend(fontsize=7, loc="upper right")
    axes[1].set_xlabel("time (s)")
    for ax in axes:
        ax.tick_params(labelsize=7)
    fig.suptitle(f"{title}: torque over limit and palm tracking in physics", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)
