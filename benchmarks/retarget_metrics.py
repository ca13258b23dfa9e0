"""The retarget and metrics steps as a run's worker runs them: CPU seconds per sequence and digests.

Computes (or reads) the collide and shape_fit steps for the first N sequences of the default
synthetic set in `--store`, then, `--repeat` times and in this thread, runs the retarget, refine
(when the default config has the critic) and metrics steps' own functions on each sequence, in run
order, as a worker of a multi-worker run does (`flows.threads.worker_threads`: one torch thread,
single-threaded BLAS), publishing each result so the next step reads it as in a run (`tasks.recent`). Each
repeat starts with empty memos (`stages._TARGETS`, `embodiments._CONTACTS_MEMO`), so the
retarget step builds its targets and the metrics step finds them, as in a run. Reports each step's CPU seconds per
sequence (`time.thread_time` around the step's function only: the figure a run's computation log
holds) and one digest of every array and attrs of the retarget and metrics results, so two
checkouts can be compared (`PYTHONPATH=<checkout>`, same store):

    python benchmarks/retarget_metrics.py --store DIR [--n 8] [--repeat 2] [--pstats out.pstats]

The first repeat includes each step's first call in this process (imports, numba cache loads; the
body and robot models are built before timing): `first_*` figures are that repeat's first sequence.
"""

from __future__ import annotations

import cProfile
import hashlib
import json
import time
from _step_bench import step_bench


def main() -> None:
    args, ctx, pipeline, shared, records = step_bench(__doc__.splitlines()[0],
                                                      "retarget-metrics", 8)

    from embody.flows.threads import worker_threads
    from embody.metrics import embodiments
    from embody.store.artifacts import array_digest, jsonable
    from embody.tasks import stages
    from embody.tasks.execute import _load_inputs, record_key, run_batch

    timed = [s for s in pipeline.per_sequence if s.name in ("retarget", "refine", "metrics")]
    for s in pipeline.per_sequence:
        if s in timed:
            break
        records = run_batch(s, ctx, records, shared)
    for rec in records:
        if rec["status"] != "ok":
            raise SystemExit(f"{rec['id']}: {rec['error']}")

    cpu: dict[str, list[float]] = {s.name: [] for s in timed}
    first: dict[str, float] = {}
    digests: dict[str, dict[str, str]] = {}
    prof = None
    with worker_threads(2):
        for r in range(args.repeat):
            if args.pstats and r == args.repeat - 1:
                prof = cProfile.Profile(time.thread_time)
            with stages._TARGETS_LOCK:
                stages._TARGETS.clear()
            embodiments.__dict__.get("_CONTACTS_MEMO", {}).clear()  # the human contacts' memo too
            spent = {s.name: 0.0 for s in timed}
            for i, rec in enumerate(records):
                keys = dict(rec["keys"])
                for step in timed:
                    key, input_keys = record_key(step, ctx, {**rec, "keys": keys}, shared)
                    ctx.store.remove(step.name, key)
                    inputs = _load_inputs(step, ctx, input_keys)
                    c = time.thread_time()
                    if prof:
                        prof.enable()
                    result = step.compute(ctx, inputs)
                    if prof:
                        prof.disable()
                    took = time.thread_time() - c
                    spent[step.name] += took
                    if r == 0 and i == 0:
                        first[step.name] = took
                    arrays, attrs = result.to_arrays(), result.to_attrs()
                    ctx.store.publish(step.name, key, arrays, attrs, {
                        "inputs": input_keys, "config": step.config(ctx.cfg),
                        "version": step.version, "run": ctx.run, "sequence": rec["id"],
                        "metrics": jsonable(step.metrics(result))})
                    keys[step.name] = key
                    now = {k: array_digest(v) for k, v in arrays.items()}
                    if step.name != "refine":  # the refine step's attrs hold timings
                        now["attrs"] = hashlib.sha256(json.dumps(jsonable(attrs), sort_keys=True)
                                                      .encode()).hexdigest()
                    name = f"{rec['id']}/{step.name}"
                    if name in digests and digests[name] != now:
                        raise SystemExit(f"{name}: differs between repeats")
                    digests[name] = now
            for s in timed:
                cpu[s.name].append(spent[s.name] / len(records))
    if args.digests:
        for name, d in sorted(digests.items()):
            for k, v in sorted(d.items()):
                print(f"{name} {k} {v[:16]}")

    def digest_of(step: str) -> str:
        part = {k: v for k, v in digests.items() if k.endswith("/" + step)}
        return hashlib.sha256(json.dumps(part, sort_keys=True).encode()).hexdigest()[:16]
    if prof and args.pstats:
        prof.dump_stats(args.pstats)
    best = {k: min(v) for k, v in cpu.items()}
    both = best["retarget"] + best["metrics"]
    print("RESULT " + " ".join(
        [f"{k}_cpu_s_per_seq={v:.3f}" for k, v in best.items()]
        + [f"retarget_plus_metrics_cpu_s={both:.3f}"]
        + [f"first_{k}_cpu_s={v:.3f}" for k, v in first.items()]
        + [f"repeats={args.repeat}", f"n={len(records)}", f"retarget_digest={digest_of('retarget')}",
           f"metrics_digest={digest_of('metrics')}"]))


if __name__ == "__main__":
    main()
