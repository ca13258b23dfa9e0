"""Animated previews: MP4 through imageio-ffmpeg when installed, else GIF/WebP through Pillow.

Frames are streamed to the encoder as they are drawn, so a long sequence at the source frame rate
never sits in memory whole (GIF/WebP, the fallbacks, still collect theirs).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from PIL import Image

log = logging.getLogger(__name__)

#: x264 settings: `veryfast` encodes these flat-shaded frames several times faster than the
#: default preset at a similar size; one thread and `-bitexact` keep the bytes reproducible.
#: Measured on 166 preview frames (1280×480): veryfast 7.4 ms/frame, 176 KB; ultrafast with
#: `-tune animation` 5.3 ms/frame but 689 KB: 4× the store for 2 ms a frame, so not taken.
#: Without B-frames (81 frames at 15 fps, CPU ms a frame, medians of 6): 4.3 instead of 5.3
#: for 157 instead of 136 KB; ultrafast 3.2 for 467 KB.
_X264 = ["-preset", "veryfast", "-crf", "23", "-x264-params", "bframes=0", "-threads", "1",
         "-bitexact"]


class PreviewWriter:
    """Write frames (N,H,W,3) uint8 batch by batch; `close()` returns the path written (its
    suffix is the format used: mp4 falls back to gif without imageio-ffmpeg)."""

    def __init__(self, path: str | Path, fps: float, fmt: str = "mp4") -> None:
        self.path, self.fps, self.fmt = Path(path), float(fps), fmt
        self._writer = None
        self._images: list[Image.Image] = []
        if fmt == "mp4":
            try:
                import imageio_ffmpeg  # noqa: F401
            except ImportError:
                log.warning("imageio-ffmpeg not installed: writing a GIF preview instead")
                self.fmt = "gif"
        self.out = self.path.with_suffix("." + self.fmt)

    def add(self, frames: np.ndarray) -> None:
        frames = np.ascontiguousarray(frames, dtype=np.uint8)
        if self.fmt != "mp4":
            self._images += [Image.fromarray(f) for f in frames]
            return
        if self._writer is None:
            import imageio_ffmpeg
            h, w = frames.shape[1:3]
            self._writer = imageio_ffmpeg.write_frames(
                str(self.out), (w, h), fps=self.fps, codec="libx264", pix_fmt_out="yuv420p",
                macro_block_size=2, ffmpeg_log_level="error", output_params=list(_X264))
            self._writer.send(None)
        for frame in frames:
            self._writer.send(frame)

    def close(self) -> Path:
        if self.fmt == "mp4":
            if self._writer is None:
                raise ValueError("no preview frames were written")
            self._writer.close()
            return self.out
        if not self._images:
            raise ValueError("no preview frames were written")
        self._images[0].save(self.out, format=self.fmt.upper(), save_all=True,
                             append_images=self._images[1:], duration=int(round(1000 / self.fps)),
                             loop=0, **({"lossless": True} if self.fmt == "webp" else {}))
        return self.out


def write_preview(frames: np.ndarray, path: str | Path, fps: float, fmt: str = "mp4") -> Path:
    """Write frames (N,H,W,3) uint8; returns the path actually written (suffix = format used)."""
    writer = PreviewWriter(path, fps, fmt)
    writer.add(frames)
    return writer.close()
