"""The render step alone, on a finished run's stored inputs: CPU seconds per sequence, all of it.

`pipeline.py`'s `render_cpu_s` is the worker thread's CPU only: llvmpipe's raster threads and the
x264 encoder child run beside it on the same cores. This runs the pipeline's own render step
(`tasks.stages.RENDER_REFINED`, with the worker's kept renderer, `render.record.kept_renderer`)
in one process over the first N sequences whose refine step a store holds, and prints this
process's CPU (threads and finished children) per sequence, the worker thread's share, and the
first sequence apart (it opens the renderer: GL context, shaders, the reference mesh). The robot's
drawn model is built before timing, as the worker zygote does (`tasks.stages.warm`). With
`--profile FILE` the timed sequences run under cProfile on thread CPU time. The sheet and
preview digests are printed so two checkouts can be compared for the same bytes.

    python benchmarks/render_step.py --store STORE [--n 4] [--profile out.pstats]

STORE is a store a default run filled (e.g. `pipeline.py --out DIR` leaves DIR/store).
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import os
import pstats
import time
from pathlib import Path


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, required=True)
    parser.add_argument("--n", type=int, default=4, help="Sequences (the first is timed apart).")
    parser.add_argument("--profile", type=Path, default=None, help="Write cProfile stats here.")
    args = parser.parse_args()

    import torch
    from threadpoolctl import threadpool_limits

    from embody.config import Config
    from embody.render.record import kept_renderer
    from embody.render.scene import prepared_robot_model
    from embody.store import ArtifactStore
    from embody.tasks.pipeline import Context
    from embody.tasks.stages import RENDER_REFINED as step

    torch.set_num_threads(1)  # as in the pipeline's workers
    threadpool_limits(limits=1, user_api="blas")
    store = ArtifactStore(args.store)
    rows = store.computations("refine")[: args.n]
    if len(rows) < 2:
        raise SystemExit(f"{args.store}: fewer than 2 refine artifacts")
    ctx = Context(Config.model_validate({"run": {"store": str(args.store)}}), str(args.store),
                  "bench-render")
    inputs = []
    for row in rows:
        keys = dict(store.info("refine", row["key"])["inputs"], refine=row["key"])
        loaded = {}
        for s in step.inputs:
            art = store.read(s.name, keys[s.name])
            loaded[s.name] = s.load(art.arrays, art.attrs)
        inputs.append(loaded)
    ctx.body  # the models load before timing, as in a warmed worker
    prepared_robot_model(ctx.robot, ctx.cfg.render, ctx.robot.spec.torso_body)
    profile = cProfile.Profile(time.thread_time) if args.profile else None
    results = []
    with kept_renderer():
        c0, t0 = _cpu(), time.thread_time()
        results.append(step.compute(ctx, inputs[0]))
        first_cpu, first_thread = _cpu() - c0, time.thread_time() - t0
        c0, t0, w0 = _cpu(), time.thread_time(), time.perf_counter()
        if profile is not None:
            profile.enable()
        for loaded in inputs[1:]:
            results.append(step.compute(ctx, loaded))
        if profile is not None:
            profile.disable()
        n = len(inputs) - 1
        cpu, thread, wall = _cpu() - c0, time.thread_time() - t0, time.perf_counter() - w0
    for row, r in zip(rows, results):
        print(f"{row.get('sequence')}: sheet {hashlib.sha256(r.sheet_png).hexdigest()[:12]} "
              f"({len(r.sheet_png)} B) preview "
              f"{hashlib.sha256(r.preview or b'').hexdigest()[:12]} ({len(r.preview or b'')} B)")
    if profile is not None:
        profile.dump_stats(args.profile)
        pstats.Stats(profile).sort_stats("tottime").print_stats(20)
    print(f"RESULT render_cpu_s={cpu / n:.3f} render_thread_cpu_s={thread / n:.3f} "
          f"render_wall_s={wall / n:.3f} first_cpu_s={first_cpu:.2f} "
          f"first_thread_cpu_s={first_thread:.2f} sequences={n} load1={os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
