"""Steps and pipelines as the orchestrator sees them (no Prefect here).

A `Step` names a stage, its code version, the config sections it reads, its upstream steps and
two callables: `compute(ctx, inputs) -> result` (one library call) and `load(arrays, attrs)`
(the result's `from_arrays`). Adding a stage to the pipeline means writing one such definition.
"""

from __future__ import annotations

import threading
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from embody.config import Config
from embody.store.artifacts import ArtifactStore
from embody.store.keys import content_key, files_key

__all__ = ["Context", "Pipeline", "Step", "resource"]

#: Expensive per-process objects (body model, robot), keyed by what determines them.
_RESOURCES: dict[tuple[str, str], Any] = {}
#: One lock per slot: a worker thread asking for a model another thread is building waits for it
#: instead of building a second copy (a run's two workers start their first steps at once).
_SLOT_LOCKS: dict[tuple[str, str], threading.Lock] = {}
_LOCKS_LOCK = threading.Lock()


def resource(name: str, identity: str, factory: Callable[[], Any]) -> Any:
    """Build `factory()` once per process and identity; batches in one worker share it."""
    slot = (name, identity)
    if slot in _RESOURCES:
        return _RESOURCES[slot]
    with _LOCKS_LOCK:
        lock = _SLOT_LOCKS.setdefault(slot, threading.Lock())
    with lock:
        if slot not in _RESOURCES:
            _RESOURCES[slot] = factory()
    return _RESOURCES[slot]


def _default_metrics(result: Any) -> dict[str, Any]:
    metrics = getattr(result, "metrics", None)
    return dict(metrics) if isinstance(metrics, Mapping) else {}


@dataclass(frozen=True)
class Step:
    """One stage: how to key it, compute it and load its stored result."""

    name: str
    #: Bump by hand whenever the step's output changes for the same inputs and config.
    version: str
    #: Config sections whose canonical JSON enters the content key.
    sections: tuple[str, ...]
    compute: Callable[["Context", dict[str, Any]], Any] = field(repr=False)
    load: Callable[[dict[str, Any], dict[str, Any]], Any] = field(repr=False)
    #: Upstream steps whose results `compute` receives, by name.
    inputs: tuple["Step", ...] = ()
    #: Computed once per run (e.g. the shape fit per robot + body), not per sequence.
    shared: bool = False
    metrics: Callable[[Any], dict[str, Any]] = field(default=_default_metrics, repr=False)
    #: Files the config points at whose bytes matter too (e.g. the robot definition YAML).
    files: Callable[[Config], list[Path]] | None = field(default=None, repr=False)
    #: The process that computed it keeps what the same sequences' later steps reuse (its
    #: memos, its recent arrays), so worker processes route those steps back to it
    #: (`tasks.workers`); False for a step whose process keeps nothing they read.
    affinity: bool = True

    def key(self, cfg: Config, input_keys: Mapping[str, str]) -> str:
        return content_key(self.name, self.version, self.config(cfg), input_keys)

    def config(self, cfg: Config) -> dict[str, str]:
        """What of the configuration enters the key: section JSON, plus referenced files' bytes."""
        out = {s: cfg.section_json(s) for s in self.sections}
        if self.files is not None:
            out["files"] = files_key(p for p in self.files(cfg) if Path(p).is_file())
        return out


@dataclass(frozen=True)
class Pipeline:
    """The source step (one `SequenceRef` → `Motion`) followed by the steps in run order."""

    source: Step
    steps: tuple[Step, ...]

    @property
    def per_sequence(self) -> tuple[Step, ...]:
        return (self.source,) + tuple(s for s in self.steps if not s.shared)

    @property
    def shared(self) -> tuple[Step, ...]:
        return tuple(s for s in self.steps if s.shared)

    @property
    def names(self) -> list[str]:
        return [self.source.name] + [s.name for s in self.steps]


@dataclass
class Context:
    """What every step call sees: the config, the store and the run; picklable for workers."""

    cfg: Config
    store_root: str
    run: str
    #: This run of the flow (not its name: a rerun is another session); scopes what a worker
    #: keeps of its own results in memory (`tasks.recent`).
    session: str = field(default_factory=lambda: uuid.uuid4().hex)

    def __post_init__(self) -> None:
        # The memo of `key` is no dataclass field, so Prefect's walk of a task's parameters
        # never reads it: with `return_data` that walk reads each field twice and, when the
        # driver had replaced the memo in between, rebuilt the context with
        # `dataclasses.replace`, which refuses an `init=False` field ("Failed to resolve inputs
        # in parameter 'ctx'": a whole batch lost on a loaded machine, 2026-11-27).
        self._configs: dict[str, dict[str, str]] = {}

    def key(self, step: Step, input_keys: Mapping[str, str]) -> str:
        """`step.key` with the step's config JSON computed once per context, not per sequence.

        The memo is replaced, never mutated, so a thread iterating an older one (the driver and
        the workers key steps concurrently) never sees it change size.
        """
        configs = self._configs
        if step.name not in configs:
            configs = {**configs, step.name: step.config(self.cfg)}
            self._configs = configs
        return content_key(step.name, step.version, configs[step.name], input_keys)

    @property
    def store(self) -> ArtifactStore:
        return ArtifactStore(self.store_root)

    @property
    def body(self) -> Any:
        from embody.body import load_body_model
        return resource("body", self.cfg.section_json("body"), lambda: load_body_model(self.cfg.body))

    @property
    def robot(self) -> Any:
        from embody.robot import load_robot
        return resource("robot", self.cfg.section_json("robot"), lambda: load_robot(self.cfg.robot))

    @property
    def critic(self) -> Any:
        """One critic per process and critic config, so the VLM request budget spans the run
        (per worker process under the process and Dask runners), not each sequence."""
        from embody.critic import make_critic
        return resource("critic", self.cfg.section_json("critic"),
                        lambda: make_critic(self.cfg.critic))
