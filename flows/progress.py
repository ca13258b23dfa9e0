"""Per-stage progress on stderr: redrawn bars on a terminal, plain lines otherwise."""

from __future__ import annotations

import sys
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """Counts of done / cached / failed sequences per stage."""

    def __init__(self, stages: list[str], total: int, stream: TextIO | None = None,
                 enabled: bool = True) -> None:
        self.stages = stages
        self.total = total
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = enabled and self.stream.isatty()
        self.counts = {s: {"done": 0, "cached": 0, "failed": 0, "printed": -1} for s in stages}
        self._drawn = 0

    def add(self, stage: str, done: int = 0, cached: int = 0, failed: int = 0) -> None:
        c = self.counts[stage]
        c["done"] += done
        c["cached"] += cached
        c["failed"] += failed
        if not self.enabled:
            return
        if self.tty:
            self._redraw()
            return
        # Plain lines at every tenth of the way (and at the end), not per batch: logs of a
        # 20k-sequence run stay short.
        finished = c["done"] + c["failed"]
        decile = 10 * finished // max(self.total, 1)
        if decile > c["printed"]:
            c["printed"] = decile
            print(self._line(stage), file=self.stream, flush=True)

    def _line(self, stage: str, width: int = 24) -> str:
        c, n = self.counts[stage], max(self.total, 1)
        finished = c["done"] + c["failed"]
        bar = "#" * int(width * finished / n)
        return (f"{stage:>10} [{bar:<{width}}] {finished}/{self.total}"
                f"  cached {c['cached']}  failed {c['failed']}")

    def _redraw(self) -> None:
        up = f"\x1b[{self._drawn}F" if self._drawn else ""
        lines = "\n".join(self._line(s) + "\x1b[K" for s in self.stages)
        self.stream.write(up + lines + "\n")
        self.stream.flush()
        self._drawn = len(self.stages)
