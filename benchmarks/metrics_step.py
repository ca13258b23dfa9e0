"""The metrics step alone, against stored inputs: CPU seconds per sequence and its output digests.

Computes (or reads) the default pipeline's steps before `metrics` for the first N sequences of the
default synthetic set in `--store`, then runs the metrics step's own function on each sequence,
`--repeat` times, in this process, and reports its CPU seconds per sequence (`time.process_time`;
a loaded shared machine inflates it far less than wall time). As in a run, the retarget step's
targets are in this process's memo (`stages._targets`) when the metrics step starts: the store
hit skips the retarget step, so they are built once before timing. Each repeat recomputes
everything else (the IK-only baseline's targets included). It prints one digest per metrics array and one of the attrs, so two checkouts'
outputs can be compared (`PYTHONPATH=<checkout>`, same store):

    python benchmarks/metrics_step.py --store DIR [--n 4] [--repeat 2] [--pstats out.pstats]
"""

from __future__ import annotations

import cProfile
import hashlib
import json
import time
from _step_bench import step_bench


def main() -> None:
    args, ctx, pipeline, shared, records = step_bench(__doc__.splitlines()[0], "metrics-step", 4)

    from embody.store.artifacts import array_digest, jsonable
    from embody.tasks import stages
    from embody.tasks.execute import _input_keys, _load_inputs, run_batch

    step = pipeline.per_sequence[-1]
    assert step.name == "metrics"
    for s in pipeline.per_sequence[:-1]:
        records = run_batch(s, ctx, records, shared)
    inputs = []
    for rec in records:
        if rec["status"] != "ok":
            raise SystemExit(f"{rec['id']}: {rec['error']}")
        got = _load_inputs(step, ctx, _input_keys(step, rec["keys"], shared))
        stages._targets(ctx, got["collide"].motion, got["shape_fit"], ctx.cfg.ik)  # as the retarget step left it
        inputs.append((rec["id"], got))

    primed = dict(stages._TARGETS)  # the retarget step's targets only: the baseline's are rebuilt
    prof = cProfile.Profile(time.process_time) if args.pstats else None
    cpu, wall, digests = [], [], {}
    for _ in range(args.repeat):
        with stages._TARGETS_LOCK:
            stages._TARGETS.clear()
            stages._TARGETS.update(primed)
        c, t = time.process_time(), time.perf_counter()
        for seq, got in inputs:
            if prof:
                prof.enable()
            result = step.compute(ctx, got)
            if prof:
                prof.disable()
            arrays = {k: array_digest(v) for k, v in result.to_arrays().items()}
            attrs = hashlib.sha256(json.dumps(jsonable(result.to_attrs()), sort_keys=True)
                                   .encode()).hexdigest()
            now = {**arrays, "attrs": attrs}
            if seq in digests and digests[seq] != now:
                raise SystemExit(f"{seq}: the metrics differ between repeats")
            digests[seq] = now
        cpu.append((time.process_time() - c) / len(inputs))
        wall.append((time.perf_counter() - t) / len(inputs))
    for seq, d in digests.items():
        if args.digests:
            for k, v in d.items():
                print(f"{seq} {k} {v[:16]}")
    every = hashlib.sha256(json.dumps(digests, sort_keys=True).encode()).hexdigest()
    if prof and args.pstats:
        prof.dump_stats(args.pstats)
    print(f"RESULT metrics_cpu_s_per_seq={min(cpu):.3f} metrics_wall_s_per_seq={min(wall):.3f} "
          f"repeats={args.repeat} n={len(inputs)} digest={every[:16]}")


if __name__ == "__main__":
    main()
