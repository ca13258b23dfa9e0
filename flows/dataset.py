"""The dataset flow: every sequence through the pipeline, batched, cached, failure-isolated.

The driver submits one task per (step, batch) and chains a batch's next step when its previous
one finishes (done-callbacks feed a queue), so stages overlap without idle waiting tasks and at
most `2 × workers` batches are in flight: a 20k-sequence dataset never queues 100k task runs.
Shared steps (the shape fit) run once; steps that need them wait until they are done.
"""

from __future__ import annotations

import errno
import functools
import os
import queue
import re
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from embody.config import Config
from embody.errors import ConfigError, EmbodyError
from embody.flows.progress import Progress
from embody.flows.verdicts import verdict_summary
from embody.io.remote import fetch_dataset, is_url
from embody.verdicts import sequence_verdicts
from embody.flows.runners import make_task_runner
from embody.store import ArtifactStore, Manifest, check_run_name
from embody.tasks.execute import cached, new_record
from embody.tasks.pipeline import Context, Pipeline
from embody.tasks.stages import default_pipeline
from embody.tasks.workers import task_threads

__all__ = ["check_run_reuse", "dataset_flow", "default_run_name", "resolve_dataset", "run_dataset",
           "run_flow", "write_tables"]

_SAVE_EVERY_S = 1.0
#: Below this many free bytes where Prefect keeps its database, its failures read as a full disk.
_FULL_BYTES = 1 << 20
#: The summaries of the flows this process ran, by run name: `run_flow` still returns one when
#: Prefect fails after the flow itself finished (e.g. recording its end in a full database).
_SUMMARIES: dict[str, dict[str, Any]] = {}


class OrchestrationError(EmbodyError):
    """Prefect (its server or its database) failed before the run could record anything."""


def orchestration_failure(exc: BaseException, store_root: str | Path,
                          what: str = "Prefect failed") -> str:
    """One line for a failure of Prefect's API or server: a full disk under its database (a
    500 from its server says no more) is named as such."""
    home = Path(os.environ.get("PREFECT_HOME") or Path(store_root) / "prefect")
    try:
        st = os.statvfs(home if home.exists() else store_root)
        full = st.f_bavail * st.f_frsize < _FULL_BYTES
    except OSError:
        full = False
    if full or getattr(exc, "errno", None) == errno.ENOSPC:
        return f"{what}: no space left on device (under {home})"
    text = " ".join(str(exc).split())
    return f"{what}: {type(exc).__name__}: {text[:200]}"


def resolve_dataset(dataset: str | Path | None, cfg: Config) -> Path:
    """The dataset path; the default synthetic set is generated into `<store>/data` once."""
    if dataset is None:
        from embody.synth import default_dataset
        return Path(default_dataset(ArtifactStore(cfg.run.store).work_dir / "data", n=cfg.run.synth_n,
                                    seed=cfg.run.seed))
    if is_url(str(dataset)):  # workers read the local mirror, never the object store
        return fetch_dataset(str(dataset))
    return Path(dataset)


def default_run_name(dataset: Path, split: str | None, robot: str | None = None) -> str:
    """`<dataset>[-<split>].<robot>`: runs of one dataset on two robots never share a name."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "-", dataset.stem or "dataset").strip("-.") or "dataset"
    name = f"{name}-{split}" if split else name
    if robot:
        name += "." + (re.sub(r"[^A-Za-z0-9_-]+", "-", robot).strip("-") or "robot")
    return name


def run_name(cfg: Config, dataset: str | Path, split: str | None) -> str:
    """The run's name: `run.name`, else the default; validated (no `.`/`..`, nothing outside runs/)."""
    if cfg.run.name:
        return check_run_name(cfg.run.name)
    return check_run_name(default_run_name(Path(dataset), split, cfg.robot.name))


def check_run_reuse(store_root: str | Path, run: str, dataset: str | Path, split: str | None,
                    robot: str, overwrite: bool = False) -> None:
    """Refuse (ConfigError, exit 2) to reuse a run name of another robot or dataset, unless told."""
    import json
    try:
        text = None if overwrite else ArtifactStore(store_root).read_manifest_text(run)
        old = json.loads(text) if text is not None else None
    except (OSError, ValueError):
        return  # unreadable: nothing to protect
    if not isinstance(old, dict):
        return
    old_robot = ((old.get("config") or {}).get("robot") or {}).get("name")
    old_data = old.get("dataset")
    what = []
    if old_robot and old_robot != robot:
        what.append(f"robot {old_robot!r} (now {robot!r})")
    if old_data and Path(old_data).expanduser().resolve() != Path(dataset).expanduser().resolve():
        what.append(f"dataset {old_data} (now {Path(dataset).resolve()})")
    if old.get("split", split) != split:
        what.append(f"split {old.get('split')!r} (now {split!r})")
    if what:
        raise ConfigError("run.name", f"run {run!r} already holds a run of another " +
                          " and ".join(what) + ": pick another --name, or pass --overwrite "
                          "to replace it")


#: The task-run budget of a flow run with no `run.max_task_runs` bound.
_UNBOUNDED = 1 << 30


class _Driver:
    """The event loop of one flow run: advances each batch step by step.

    A step whose results are all in the store is resolved here without a task (warm reruns
    submit nothing); otherwise one task run computes it for the batch. Work that becomes ready
    goes through `ready`, so long chains of hits never recurse.
    """

    def __init__(self, pipeline: Pipeline, ctx: Context, manifest: Manifest, progress: Progress,
                 max_inflight: int, workers: int = 1) -> None:
        self.pipeline, self.ctx, self.manifest, self.progress = pipeline, ctx, manifest, progress
        self.workers = workers
        self.steps = pipeline.per_sequence
        self.max_inflight = max_inflight
        self.events: queue.Queue = queue.Queue()
        self.ready: deque[tuple[int, int, list[dict[str, Any]]]] = deque()
        self.outstanding = 0
        self.shared: dict[str, dict[str, Any]] = {}
        self.parked: list[tuple[int, int, list[dict[str, Any]]]] = []
        self.computed: dict[str, int] = {s.name: 0 for s in self.steps + pipeline.shared}
        self.batches: list[list[dict[str, Any]]] = []
        #: The step each batch was last submitted to (a finished batch: past the last).
        self.step_of: dict[int, int] = {}
        self.next_batch = self.inflight = 0
        self._saved = time.monotonic()
        self._save_every = _SAVE_EVERY_S
        self.recovered = 0
        self.save_error: str | None = None
        #: Task runs this flow run may still be given (`run.max_task_runs`, `flows.chunks`)
        #: and the most the batches of this `run` call can need: tail splits stay within it.
        self.budget, self.planned = _UNBOUNDED, 0

    def run(self, batches: list[list[dict[str, Any]]], budget: int | None = None) -> None:
        """Drive `batches` to the end (one chunk of a run: `flows.chunks`)."""
        self.batches = batches
        self.step_of, self.next_batch, self.inflight = {}, 0, 0
        unsubmitted = sum(s.name not in self.shared for s in self.pipeline.shared)
        self.planned = len(batches) * len(self.steps) + unsubmitted
        self.budget = budget if budget is not None else _UNBOUNDED
        self._submit_shared()
        self._fill()
        while self.ready or self.outstanding:
            while self.ready:
                self._advance(*self.ready.popleft())
            if self.outstanding:
                tag, fut = self.events.get()
                self.outstanding -= 1
                if tag[0] == "shared":
                    self._on_shared(tag[1], fut)
                else:
                    self._on_batch(tag[1], tag[2], fut)

    def _watch(self, future: Any, tag: tuple) -> None:
        self.outstanding += 1
        future.add_done_callback(lambda f: self.events.put((tag, f)))

    def _shared_keys(self) -> dict[str, str]:
        return {n: r["key"] for n, r in self.shared.items() if r["status"] == "ok"}

    def _submit_shared(self) -> None:
        for step in self.pipeline.shared:
            if step.name in self.shared or any(s.name not in self.shared for s in step.inputs):
                continue
            self.shared[step.name] = {"status": "running"}
            from embody.tasks.steps import shared_task  # Prefect: imported once a task is needed
            fut = shared_task(step).submit(step, self.ctx, self._shared_keys())
            self._watch(fut, ("shared", step.name))

    def _fill(self) -> None:
        while self.inflight < self.max_inflight and self.next_batch < len(self.batches):
            self.ready.append((self.next_batch, 0, self.batches[self.next_batch]))
            self.next_batch += 1
            self.inflight += 1

    def _advance(self, b: int, i: int, records: list[dict[str, Any]]) -> None:
        step = self.steps[i]
        needs = [s.name for s in step.inputs if s.shared]
        if any(self.shared.get(n, {}).get("status") in (None, "running") for n in needs):
            self.parked.append((b, i, records))
            return
        broken = [self.shared[n] for n in needs if self.shared[n]["status"] != "ok"]
        if broken:
            for rec in records:
                if rec["status"] == "ok":
                    rec.update(status="failed", failed_step=step.name, error=broken[0]["error"])
            self._complete(b, i, records)
            return
        if not any(r["status"] == "ok" for r in records):  # nothing left to do in this batch
            self._complete(b, i, records)
            return
        hits = cached(step, self.ctx, records, self._shared_keys())
        if hits is not None:
            self._complete(b, i, hits)
            return
        half = self._split(b, i, records)
        if half is not None:  # the other half goes on as a batch of its own
            self.ready.append((len(self.batches) - 1, i, half))
            records = self.batches[b]
        from embody.tasks.steps import batch_task  # Prefect: imported once a task is needed
        fut = batch_task(step, b).submit(step, self.ctx, records, self._shared_keys())
        self._watch(fut, ("batch", b, i))

    def _split(self, b: int, i: int, records: list[dict[str, Any]]
               ) -> list[dict[str, Any]] | None:
        """At the run's tail (every batch started), split a batch in two when a worker would
        idle or when the batch lags (another batch is past step `i` already): otherwise the
        last batch runs its steps one sequence after another on one worker while the others
        wait (the default run's last render batch: ~3-5 s with one of two workers idle).
        Returns the second half, appended to `batches`; `batches[b]` becomes the first half."""
        self.step_of[b] = i
        ok = [r for r in records if r["status"] == "ok"]
        if self.workers < 2 or len(ok) < 2 or self.next_batch < len(self.batches):
            return None
        if self.planned + len(self.steps) - i > self.budget:  # the flow run's task-run bound
            return None
        busy = self.outstanding + len(self.ready) + 1  # this batch's task included
        lags = any(step > i for other, step in self.step_of.items() if other != b)
        if busy >= self.workers and not lags:
            return None
        keep = ok[: len(ok) // 2]
        first = [r for r in records if r["status"] != "ok"] + keep
        second = ok[len(ok) // 2:]
        self.batches[b] = first
        self.batches.append(second)
        self.step_of[len(self.batches) - 1] = i
        self.planned += len(self.steps) - i
        self.next_batch = len(self.batches)
        self.inflight += 1
        return second

    def _complete(self, b: int, i: int, records: list[dict[str, Any]]) -> None:
        name = self.steps[i].name
        ok = [r for r in records if r["status"] == "ok" and name in r["keys"]]
        computed = sum(name in r["computed"] for r in ok)
        failed = sum(r.get("failed_step") == name for r in records)
        self.computed[name] += computed
        self.progress.add(name, done=len(ok), cached=len(ok) - computed, failed=failed)
        for rec in records:
            self.manifest.update(rec)
            self.recovered += len(rec.get("recovered", ()))
            rec.pop("recovered", None)
        if i + 1 < len(self.steps):
            self.ready.append((b, i + 1, records))
            self._save()  # each finished step's keys, not only finished sequences
            return
        for rec in records:
            self.manifest.finish_sequence(rec["id"])
        self.step_of[b] = len(self.steps)  # done: every other batch lags behind it
        self.inflight -= 1
        self._fill()
        self._save()

    def abandon(self, error: str) -> None:
        """The orchestration failed mid-run: every sequence not finished fails with `error`
        (what finished stays recorded)."""
        for seq in self.manifest.sequences.values():
            if seq["status"] == "pending":
                seq.update(status="failed", error=error, failed_step=seq["failed_step"] or "prefect")

    def _save(self, force: bool = False) -> None:
        """Save the manifest at most every `_save_every` s; a full disk is reported, not fatal."""
        if not force and time.monotonic() - self._saved <= self._save_every:
            return
        t0 = time.monotonic()
        try:
            self.manifest.save()
        except OSError as exc:
            self.save_error = f"manifest not saved: {exc.strerror or exc}"
            return
        self._saved = time.monotonic()
        # Big manifests take long to write: keep saving under ~5% of the driver's time.
        self._save_every = max(_SAVE_EVERY_S, 20 * (self._saved - t0))

    def _on_shared(self, name: str, fut: Any) -> None:
        try:
            rec = fut.result()
        except Exception as exc:  # the task itself crashed (worker lost, unpicklable, ...)
            rec = {"step": name, "status": "failed", "key": None, "computed": False,
                   "metrics": {}, "error": f"{name}: task crashed: {type(exc).__name__}: {exc}"}
        self.shared[name] = rec
        self.manifest.set_shared(name, rec.get("key"))
        self._save(force=True)  # the shared fit is recorded as soon as it exists
        self.computed[name] += int(bool(rec.get("computed")))
        self._submit_shared()
        self.ready.extend(self.parked)
        self.parked = []

    def _on_batch(self, b: int, i: int, fut: Any) -> None:
        try:
            records = fut.result()
        except Exception as exc:
            name = self.steps[i].name
            records = [dict(r, status="failed", failed_step=name,
                            error=f"{name}: task crashed: {type(exc).__name__}: {exc}")
                       if r["status"] == "ok" else r for r in self._batch_input(b)]
        self._complete(b, i, records)

    def _batch_input(self, b: int) -> list[dict[str, Any]]:
        # A crashed task returns nothing: fall back to the manifest's view of the batch.
        out = []
        for rec in self.batches[b]:
            seq = self.manifest.sequences[rec["id"]]
            out.append({"id": rec["id"], "status": "ok" if seq["status"] == "pending" else "failed",
                        "error": seq["error"], "failed_step": seq["failed_step"],
                        "keys": dict(seq["steps"]), "metrics": dict(seq["metrics"]), "computed": []})
        return out


def write_tables(store: ArtifactStore, run: str, manifest: Manifest | None = None) -> Path:
    """`runs/<run>/sequences.csv`: one row per sequence, status, error and every scalar metric."""
    import pandas as pd

    from embody.csvsafe import csv_safe
    manifest = manifest or Manifest.load(store, run)
    rows = []
    for sid, seq in manifest.sequences.items():
        row = {"id": sid, "status": seq["status"], "failed_step": seq["failed_step"],
               "error": seq["error"], **sequence_verdicts(seq)}
        for step, metrics in seq["metrics"].items():
            row.update({f"{step}.{k}": v for k, v in metrics.items()
                        if isinstance(v, (int, float, str, bool)) or v is None})
        rows.append(row)
    text = csv_safe(pd.DataFrame(rows)).to_csv(index=False, float_format="%.10g")  # no float noise
    return store.write_run_file(run, "sequences.csv", text.encode("utf-8"))


def build_report(store: ArtifactStore, run: str) -> tuple[str | None, str | None]:
    """The report module's tables and figures, when it is installed: (where, error)."""
    try:
        from embody.report import build_report as build
    except ImportError:
        return None, None
    if ".ablation-" in run:  # `report --ablation`'s internal runs: their report is Table II
        return None, None
    try:
        paths = build(store.root, run, reuse=True)
    except Exception as exc:  # a report problem must not turn finished work into a failure
        return None, f"{type(exc).__name__}: {exc}"
    return str(getattr(paths, "out_dir", paths)), None


def start_manifest(store: ArtifactStore, run: str, refs: list[Any], dataset: str | Path,
                   split: str | None, pipeline: Pipeline, cfg: Config) -> Manifest:
    """A new manifest for `run` over `refs` (what every run, flow or cached, records first)."""
    manifest = Manifest(store, run)
    manifest.start([r.id for r in refs], dataset=str(Path(dataset).expanduser().resolve()),
                   split=split, steps=pipeline.names, config=cfg.model_dump(mode="json"))
    return manifest


def finish_run(store: ArtifactStore, run: str, manifest: Manifest, cfg: Config, *,
               dataset: str | Path, split: str | None, t0: float, computed: dict[str, int],
               shared: dict[str, Any], prefect: bool, errors: list[str] | None = None
               ) -> dict[str, Any]:
    """Save the finished manifest, write `sequences.csv` and the report, and return the run's
    summary: the one bookkeeping both the flow and the cached path (`flows.warm`) do."""
    errors = list(errors or [])
    table: Path | None = None
    try:  # a full disk here still ends with the summary and the failure table (exit 1)
        manifest.save(finished=True)
        errors = []
        table = write_tables(store, run)  # from disk: concurrent writers' sequences merged
    except OSError as exc:
        reason = "no space left on device" if exc.errno == errno.ENOSPC else str(exc)
        errors.append(f"run bookkeeping not written ({reason})")
    t_report = time.perf_counter()
    report, report_error = (build_report(store, run) if cfg.run.report and not errors
                            else (None, None))
    report_s = time.perf_counter() - t_report
    seqs = manifest.sequences
    failures = [{"id": i, "step": s["failed_step"], "error": s["error"]}
                for i, s in seqs.items() if s["status"] != "ok"]
    recovered = [{"id": i, "artifact": a} for i, s in seqs.items() for a in s.get("recovered", [])]
    return {"run": run, "store": str(store.root), "dataset": str(dataset), "split": split,
            "total": len(seqs), "ok": len(seqs) - len(failures), "failed": len(failures),
            "failures": failures, "computed": computed, "shared": shared,
            "manifest": str(manifest.path), "table": str(table) if table else None,
            "errors": errors, "recovered": recovered,
            "report": report, "report_error": report_error,
            "report_s": round(report_s, 3), "elapsed_s": round(time.perf_counter() - t0, 3),
            "prefect": prefect, **verdict_summary(manifest)}


def run_dataset(dataset: str | Path, *, cfg: Config, split: str | None = None,
                pipeline: Pipeline | None = None, progress: bool = False) -> dict[str, Any]:
    """Run the pipeline over a dataset inside the current flow; returns the run summary."""
    from embody.io import load_dataset

    from embody.flows.env import register_server
    from embody.flows.threads import worker_threads

    t0 = time.perf_counter()
    store = ArtifactStore(cfg.run.store)
    data = load_dataset(dataset, split, cfg.io)
    refs = list(data)[cfg.run.offset:]
    refs = refs[: cfg.run.limit] if cfg.run.limit else refs
    run = run_name(cfg, dataset, split)
    pipeline = pipeline or default_pipeline(critic=cfg.run.critic, render=cfg.run.render)
    ctx = Context(cfg=cfg, store_root=str(store.root), run=run)
    register_server()  # so a later run can stop this one's Prefect server if we are killed
    manifest = start_manifest(store, run, refs, dataset, split, pipeline, cfg)
    # small runs: at least two batches per worker, so no worker idles while one runs a long batch
    size = min(cfg.run.batch_size, max(1, -(-len(refs) // (2 * cfg.run.workers))))
    batches = [[new_record(r) for r in refs[i:i + size]] for i in range(0, len(refs), size)]
    bar = Progress([s.name for s in pipeline.per_sequence], len(refs), enabled=progress)
    driver = _Driver(pipeline, ctx, manifest, bar, max_inflight=2 * cfg.run.workers,
                     workers=cfg.run.workers)
    from embody.tasks.workers import worker_pool
    failure = None
    from embody.flows.chunks import plan_chunks, run_chunks
    bound = cfg.run.max_task_runs
    chunks = plan_chunks(batches, len(pipeline.per_sequence), len(pipeline.shared), bound)
    with worker_threads(cfg.run.workers), worker_pool(ctx, pipeline):
        try:
            if len(chunks) == 1:
                driver.run(batches, bound)
            else:  # at most `bound` task runs per flow run: one subflow run per chunk
                run_chunks(run, chunks, lambda chunk: driver.run(chunk, bound),
                           lambda: make_task_runner(cfg.run, task_threads(cfg)))
        except Exception as exc:  # Prefect's API failed (its database's disk full, ...)
            failure = orchestration_failure(exc, store.root, "not finished: Prefect failed")
            driver.abandon(failure)
    summary = finish_run(store, run, manifest, cfg, dataset=dataset, split=split, t0=t0,
                         computed=driver.computed,
                         shared={n: r.get("key") for n, r in driver.shared.items()},
                         prefect=True, errors=[driver.save_error] if driver.save_error else [])
    if failure is not None:
        summary["errors"].append(failure)
    _SUMMARIES[run] = summary
    return summary


def _dataset_flow(dataset: str, split: str | None = None, config: dict[str, Any] | None = None,
                 pipeline: Pipeline | None = None, progress: bool = False) -> dict[str, Any]:
    """Prefect entry point; `config` is the full config as JSON data (deployments need JSON)."""
    from embody.flows.env import sigterm_inside_flow

    cfg = Config.model_validate(config or {})
    with sigterm_inside_flow():
        return run_dataset(dataset, cfg=cfg, split=split, pipeline=pipeline, progress=progress)


_dataset_flow.__name__ = _dataset_flow.__qualname__ = "dataset_flow"  # deployments' entrypoint


@functools.cache
def prefect_flow() -> Any:
    """The Prefect flow around `_dataset_flow`. Prefect is imported here, on first use, so
    resolving a dataset, checking the store and a fully cached run never pay for it."""
    from prefect import flow

    return flow(name="embody-dataset", persist_result=False, log_prints=False,
                validate_parameters=False)(_dataset_flow)


def __getattr__(name: str) -> Any:
    if name == "dataset_flow":  # `from flows.dataset import dataset_flow` still works
        return prefect_flow()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_flow(dataset: str | Path, cfg: Config, *, split: str | None = None,
             pipeline: Pipeline | None = None, progress: bool = False) -> dict[str, Any]:
    """Run `dataset_flow` with the task runner `cfg.run` asks for, against the configured
    Prefect API or this process's ephemeral server (`flows.ephemeral`), which boots while the
    steps' imports and models are loaded here (the thread runner's workers share them)."""
    from embody.flows.ephemeral import prefect_api

    steps = pipeline or default_pipeline(critic=cfg.run.critic, render=cfg.run.render)

    def warm() -> None:
        from embody.tasks.workers import prewarm
        ctx = Context(cfg=cfg, store_root=str(cfg.run.store), run="")
        # the worker processes' zygote first (it warms itself, `tasks.workers`): its start-up
        # is the longest, so it must not wait for the driver's Prefect imports
        zygote = prewarm(ctx, steps)
        # what a flow's first call imports (~1.3 s here), done while the server boots
        import fastapi.encoders  # noqa: F401  (Prefect's parameter serialisation)
        import prefect.flow_engine  # noqa: F401
        import prefect.task_engine  # noqa: F401
        import prefect.utilities.visualization  # noqa: F401
        prefect_flow()
        if cfg.run.runner != "threads" or zygote:  # other runners' workers: other processes
            return
        from embody.tasks.stages import warm as warm_steps
        try:
            warm_steps(ctx, steps)
        except Exception:  # a bad model is each sequence's error, reported by its step
            pass

    run = run_name(cfg, dataset, split)
    _SUMMARIES.pop(run, None)
    from embody.flows.runners import local_dask_cluster
    try:
        with prefect_api(warm=warm), _quiet_prefect(), local_dask_cluster(cfg) as cfg:
            return prefect_flow().with_options(task_runner=make_task_runner(cfg.run, task_threads(cfg)))(
                str(dataset), split, cfg.model_dump(mode="json"), pipeline, progress)
    except Exception as exc:  # Prefect itself failed: its server, its database, its API
        summary = _SUMMARIES.pop(run, None)
        if summary is None:
            raise OrchestrationError(orchestration_failure(
                exc, cfg.run.store, "the run could not start or finish under Prefect")) from None
        summary["errors"].append(orchestration_failure(
            exc, cfg.run.store, "Prefect could not record the run's end"))
        return summary


@contextmanager
def _quiet_prefect() -> Iterator[None]:
    """Prefect's flow and task run loggers off for the flow: every failure they would print
    (with a traceback, once per retry of its API) reaches the run's summary instead."""
    import logging

    loggers = [logging.getLogger(n) for n in ("prefect.flow_runs", "prefect.task_runs")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)
