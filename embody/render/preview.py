"""Animated previews: MP4 through imageio-ffmpeg when installed, else GIF/WebP through Pillow."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from PIL import Image

log = logging.getLogger(__name__)


def write_preview(frames: np.ndarray, path: str | Path, fps: float, fmt: str = "mp4") -> Path:
    """Write frames (N,H,W,3) uint8; returns the path actually written (suffix = format used)."""
    path = Path(path)
    frames = np.ascontiguousarray(frames, dtype=np.uint8)
    if fmt == "mp4":
        try:
            import imageio_ffmpeg
        except ImportError:
            log.warning("imageio-ffmpeg not installed: writing a GIF preview instead")
            fmt = "gif"
        else:
            out = path.with_suffix(".mp4")
            h, w = frames.shape[1:3]
            writer = imageio_ffmpeg.write_frames(
                str(out), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                macro_block_size=2, ffmpeg_log_level="error",
                output_params=["-threads", "1", "-bitexact"])
            writer.send(None)
            for frame in frames:
                writer.send(frame)
            writer.close()
            return out
    out = path.with_suffix("." + fmt)
    images = [Image.fromarray(f) for f in frames]
    images[0].save(out, format=fmt.upper(), save_all=True, append_images=images[1:],
                   duration=int(round(1000 / fps)), loop=0,
                   **({"lossless": True} if fmt == "webp" else {}))
    return out
