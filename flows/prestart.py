"""Work the driver does while Prefect's ephemeral server starts, instead of waiting for it.

`run_flow` blocks until the flow's Prefect server answers: 7-15 s on this machine, one core busy
in the server's own process, the run's workers idle. With the default thread runner every step
runs in this process, so during that wait a thread imports the stage libraries, builds the
per-process body and robot models (`tasks.pipeline.resource`, which the worker threads then
share) and computes the run's shared steps without inputs (the shape fit) through the same
`tasks.execute.run_shared` a task would call. The flow's driver takes those shared records from
here (`take`) instead of submitting their tasks: the store, keys, metrics and computation log are
what the task would have written. Process and Dask runners compute in other processes: no
prestart there.

The thread runs at normal priority. At nice 10 on a saturated machine its shape fit took 59 s of
wall time, and meanwhile it can hold the body and robot models' build locks that the workers'
first steps wait on (priority inversion). On a quiet machine it uses the core that the server's
start leaves idle either way.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future

from embody.config import Config
from embody.tasks.execute import run_shared
from embody.tasks.pipeline import Context, Pipeline

__all__ = ["THREAD_NAME", "Prestart", "discard", "start", "take"]

#: The prestart thread's name (the store's computation log records each computation's thread).
THREAD_NAME = "embody-prestart"

_CURRENT: "Prestart | None" = None
_LOCK = threading.Lock()


class Prestart:
    """A daemon thread warming this process for one run; `futures` holds a record per shared
    step it computes (`run_shared`'s record, as the step's task would return it)."""

    def __init__(self, cfg: Config, store_root: str, run: str, pipeline: Pipeline) -> None:
        self.config = cfg.model_dump_json()  # which run this is for (`take` checks it)
        self.store_root = store_root
        self.ctx = Context(cfg=cfg, store_root=store_root, run=run)
        self.steps = [s for s in pipeline.shared if not s.inputs]
        self.futures: dict[str, Future] = {s.name: Future() for s in self.steps}
        self.thread = threading.Thread(target=self._run, name=THREAD_NAME, daemon=True)

    def _run(self) -> None:
        for step in self.steps:
            fut = self.futures[step.name]
            try:
                fut.set_result(run_shared(step, self.ctx, {}))
            except BaseException as exc:  # noqa: BLE001 - the driver reports it as a crashed task
                fut.set_exception(exc)
        try:  # what every worker's first batch would otherwise wait for
            import embody.collision.windows  # noqa: F401
            import embody.critic  # noqa: F401
            import embody.metrics.embodiments  # noqa: F401
            import embody.render.record  # noqa: F401
            import embody.retarget.windows  # noqa: F401
            self.ctx.body, self.ctx.robot  # noqa: B018
        except Exception:  # noqa: BLE001 - a step that needs them reports the error itself
            pass

    def join(self) -> None:
        self.thread.join()


def start(cfg: Config, store_root: str, run: str, pipeline: Pipeline) -> Prestart | None:
    """Start warming this process for a run with the thread runner (None for other runners)."""
    global _CURRENT
    if cfg.run.runner != "threads":
        return None
    pre = Prestart(cfg, store_root, run, pipeline)
    with _LOCK:
        _CURRENT = pre
    pre.thread.start()
    return pre


def take(cfg: Config, store_root: str) -> dict[str, Future]:
    """The shared steps' record futures of the prestart made for this run (once), else {}."""
    global _CURRENT
    with _LOCK:
        pre, _CURRENT = _CURRENT, None
    if pre is None or pre.config != cfg.model_dump_json() or pre.store_root != store_root:
        return {}
    return dict(pre.futures)


def discard(pre: Prestart) -> None:
    """Forget `pre` if no flow took it (the flow failed before its driver ran)."""
    global _CURRENT
    with _LOCK:
        if _CURRENT is pre:
            _CURRENT = None
