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
