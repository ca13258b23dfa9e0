"""Draw many report figures at once: one plot per process, the same files as one after another.

Matplotlib draws on one core, and a run's report is mostly its per-sequence plots (two per
sequence, ~0.2 s each: 11 of the 12 s a 24-sequence report took on 2 cores, 2026-11-27). Each
plot is its own figure and file, so processes can draw them side by side. The processes are
fresh interpreters (`python -c`, this one's `sys.path`) that read their share of the jobs,
pickled, from a pipe: no fork of a process that may hold threads or GL state (a driver after its
run, a test session), and none of `multiprocessing`'s re-import of the `__main__` script.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["Job", "draw"]

#: One plot: (function of `embody.report.figures`, positional args, keyword args); the last
#: positional argument is the file it writes, which it returns.
Job = tuple[Callable[..., Path], tuple[Any, ...], dict[str, Any]]

#: Fewer plots than this are drawn here: starting a process (~1 s of imports) would not pay.
MIN_PARALLEL = 8
#: At most this many processes.
MAX_PROCESSES = 4


def _run(job: Job) -> Path:
    fn, args, kwargs = job
    return fn(*args, **kwargs)


def _serve() -> None:
    """A drawing process: its jobs from stdin, drawn in order."""
    for job in pickle.load(sys.stdin.buffer):
        _run(job)


def draw(jobs: Sequence[Job], processes: int | None = None) -> list[Path]:
    """Each job's plot, in order. `processes` None: one per core (at most `MAX_PROCESSES`)
    when there are at least `MIN_PARALLEL` jobs, else here; 1: here. A share whose process
    fails is drawn again here, so a plot that raises raises here."""
    if processes is None:
        processes = min(os.cpu_count() or 1, MAX_PROCESSES) if len(jobs) >= MIN_PARALLEL else 1
    processes = min(processes, len(jobs))
    if processes <= 1:
        return [_run(job) for job in jobs]
    shares = [list(jobs[k::processes]) for k in range(processes)]  # interleaved: even shares
    code = (f"import sys; sys.path[:] = {sys.path!r}; "
            "from embody.report.drawing import _serve; _serve()")
    procs = []
    for share in shares[1:]:
        try:
            proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        except OSError:
            proc = None
        procs.append((proc, share))
    for proc, share in procs:  # their jobs first, so they draw while this one does
        if proc is not None:
            try:
                pickle.dump(share, proc.stdin)
                proc.stdin.close()
            except OSError:
                pass
    for job in shares[0]:
        _run(job)
    for proc, share in procs:
        if proc is None or proc.wait() != 0:
            for job in share:  # again here: a figure that raises raises with its traceback
                _run(job)
    # each job writes its own path (its last positional argument)
    return [Path(job[1][-1]) for job in jobs]
