"""Run one step over a batch of sequences, using the store as the cache (no Prefect here).

Records travel between steps instead of arrays: ``{"id", "status", "error", "failed_step",
"keys": {step: key}, "metrics": {step: {...}}, "computed": [step, ...]}``. A failing sequence is
marked failed and skipped by later steps; the rest of the batch goes on.
"""

from __future__ import annotations

import time
import traceback
from typing import Any

from embody.store.artifacts import CorruptArtifact, jsonable
from embody.store.keys import files_key
from embody.tasks.pipeline import Context, Step
from embody.tasks.recent import forget, recall, remember

__all__ = ["InjectedFailure", "cached", "new_record", "record_key", "run_batch", "run_shared",
           "source_key"]


class InjectedFailure(RuntimeError):
    """Raised for ids in `debug.fail_on`, to exercise failure isolation and resume."""


def new_record(ref: Any) -> dict[str, Any]:
    """`ref` is consumed by the source step; `src` stays, so a corrupt source can be redone."""
    return {"id": ref.id, "ref": ref, "src": ref, "status": "ok", "error": None,
            "failed_step": None, "keys": {}, "metrics": {}, "computed": []}


def source_key(step: Step, ctx: Context, ref: Any) -> str:
    """Source artifacts hash their files' bytes (and the text, which the files may lack)."""
    files = tuple(ref.source_files) or (ref.path,)
    return ctx.key(step, {"files": files_key(files, extra=ref.text or "")})


def _input_keys(step: Step, keys: dict[str, str], shared: dict[str, str]) -> dict[str, str]:
    return {s.name: (shared if s.shared else keys)[s.name] for s in step.inputs}


def record_key(step: Step, ctx: Context, rec: dict[str, Any],
               shared: dict[str, str]) -> tuple[str, dict[str, str]]:
    """(key, input keys) of `step` for one sequence record."""
    if rec.get("ref") is not None:
        return source_key(step, ctx, rec["ref"]), {}
    input_keys = _input_keys(step, rec["keys"], shared)
    return ctx.key(step, input_keys), input_keys


def _copy(rec: dict[str, Any]) -> dict[str, Any]:
    return dict(rec, keys=dict(rec["keys"]), metrics=dict(rec["metrics"]),
                computed=list(rec["computed"]))


def cached(step: Step, ctx: Context, records: list[dict[str, Any]],
           shared: dict[str, str]) -> list[dict[str, Any]] | None:
    """The records advanced past `step` when every still-ok one is a store hit, else None.

    The flow's driver calls this before submitting a task, so a warm rerun runs no task at all.
    """
    store, out = ctx.store, []
    for rec in records:
        rec = _copy(rec)
        out.append(rec)
        if rec["status"] != "ok":
            continue
        if rec["id"] in ctx.cfg.debug.fail_on and step.name == ctx.cfg.debug.fail_step:
            return None
        try:
            key, _ = record_key(step, ctx, rec, shared)
        except Exception:  # let the task record the error
            return None
        if not store.has(step.name, key) or not store.intact(step.name, key):
            return None  # a miss, or a damaged artifact the task recomputes
        rec["keys"][step.name] = key
        rec["metrics"][step.name] = store.info(step.name, key).get("metrics", {})
    for rec in out:
        rec.pop("ref", None)
    return out


def _compute(step: Step, ctx: Context, key: str, inputs: dict[str, Any], input_keys: dict[str, str],
             seq_id: str | None, reason: str = "miss") -> dict[str, Any]:
    """Compute, publish and count one artifact; returns its metrics."""
    store = ctx.store
    t0, c0 = time.perf_counter(), time.thread_time()
    result = step.compute(ctx, inputs)
    compute_s = time.perf_counter() - t0
    # CPU seconds of this worker thread (not GL's raster threads or the encoder child): far
    # less sensitive than wall time to other jobs on a shared machine
    cpu_s = time.thread_time() - c0
    metrics = jsonable(step.metrics(result))
    arrays = result.to_arrays()
    published = store.publish(step.name, key, arrays, result.to_attrs(), {
        "inputs": input_keys, "config": step.config(ctx.cfg), "version": step.version,
        "timings": {"compute_s": compute_s}, "run": ctx.run, "sequence": seq_id, "metrics": metrics})
    store.record(step.name, key, sequence=seq_id, run=ctx.run, compute_s=compute_s,
                 cpu_s=cpu_s, published=published, reason=reason)
    if published:  # what another writer published first is read from the store
        remember(ctx.session, step.name, key, arrays)
    return metrics


def _recovered(step_name: str, key: str, problem: str) -> str:
    return f"{step_name}/{key[:12]}: {problem}"


def _load_inputs(step: Step, ctx: Context, input_keys: dict[str, str],
                 rec: dict[str, Any] | None = None,
                 shared: dict[str, str] | None = None) -> dict[str, Any]:
    """Read `step`'s inputs, each array checked against its digest. A corrupt input is a cache
    miss: it is removed and recomputed from its own inputs (recursively), and `rec` says so."""
    store, out = ctx.store, {}
    for s in step.inputs:
        key = input_keys[s.name]
        arrays = recall(ctx.session, s.name, key)
        if arrays is not None:  # published by this worker in this run
            out[s.name] = s.load(arrays, store.attrs(s.name, key))
            continue
        try:
            art = store.read(s.name, key)
        except CorruptArtifact as exc:
            if rec is None:
                raise
            store.remove(s.name, key)
            if s.shared:
                inputs = _load_inputs(s, ctx, _input_keys(s, {}, shared or {}), rec, shared)
                seq_id = None
            elif not s.inputs:  # the source step: its files
                if rec.get("src") is None:
                    raise
                inputs, seq_id = {"ref": rec["src"]}, rec["id"]
            else:
                inputs = _load_inputs(s, ctx, _input_keys(s, rec["keys"], shared or {}), rec,
                                      shared)
                seq_id = rec["id"]
            _compute(s, ctx, key, inputs, _input_keys(s, rec["keys"], shared or {})
                     if s.inputs else {}, seq_id, reason="corrupt")
            rec.setdefault("recovered", []).append(_recovered(s.name, key, exc.problem))
            art = store.read(s.name, key)
        out[s.name] = s.load(art.arrays, art.attrs)
    return out


def run_batch(step: Step, ctx: Context, records: list[dict[str, Any]],
              shared: dict[str, str]) -> list[dict[str, Any]]:
    """Apply `step` to every still-ok record: a store hit only reads metrics, a miss computes."""
    store = ctx.store
    fail_step = ctx.cfg.debug.fail_step
    out = []
    for rec in records:
        rec = _copy(rec)
        out.append(rec)
        if rec["status"] != "ok":
            continue
        try:
            if rec["id"] in ctx.cfg.debug.fail_on and step.name == fail_step:
                raise InjectedFailure(f"debug.fail_on lists {rec['id']!r}")
            key, input_keys = record_key(step, ctx, rec, shared)
            reason = "miss"
            if store.has(step.name, key) and not store.intact(step.name, key):
                store.remove(step.name, key)  # damaged: recompute it like a miss
                forget(ctx.session, step.name, key)
                rec.setdefault("recovered", []).append(
                    _recovered(step.name, key, "chunk files missing or truncated"))
                reason = "corrupt"
            if store.has(step.name, key):
                metrics = store.info(step.name, key).get("metrics", {})
            else:
                inputs = ({"ref": rec["ref"]} if rec.get("ref") is not None
                          else _load_inputs(step, ctx, input_keys, rec, shared))
                metrics = _compute(step, ctx, key, inputs, input_keys, rec["id"], reason)
                rec["computed"].append(step.name)
            rec["keys"][step.name] = key
            rec["metrics"][step.name] = metrics
        except Exception as exc:  # isolate: this sequence fails, the batch goes on
            rec.update(status="failed", failed_step=step.name,
                       error=f"{step.name}: {type(exc).__name__}: {exc}",
                       traceback=traceback.format_exc(limit=8))
        rec.pop("ref", None)
    return out


def run_shared(step: Step, ctx: Context, shared: dict[str, str]) -> dict[str, Any]:
    """Compute (or hit) a once-per-run step; same record shape without an id."""
    rec: dict[str, Any] = {"step": step.name, "status": "ok", "error": None, "key": None,
                           "metrics": {}, "computed": False}
    try:
        input_keys = _input_keys(step, {}, shared)
        key = ctx.key(step, input_keys)
        if ctx.store.has(step.name, key) and not ctx.store.intact(step.name, key):
            ctx.store.remove(step.name, key)
        if ctx.store.has(step.name, key):
            rec["metrics"] = ctx.store.info(step.name, key).get("metrics", {})
        else:
            rec["metrics"] = _compute(step, ctx, key, _load_inputs(step, ctx, input_keys),
                                      input_keys, None)
            rec["computed"] = True
        rec["key"] = key
    except Exception as exc:
        rec.update(status="failed", error=f"{step.name}: {type(exc).__name__}: {exc}",
                   traceback=traceback.format_exc(limit=8))
    return rec
