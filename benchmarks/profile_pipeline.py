"""Profile of the default pipeline's per-sequence steps, in one process, with cProfile.

All figures are CPU seconds (`time.process_time`: this process's threads, so llvmpipe's render
threads count, the ffmpeg encoder child does not), which a loaded shared machine inflates far
less than wall time; wall seconds per step are printed beside them. Torch runs on one thread, as
in the pipeline's workers. Compiled kernels load from numba's cache: run it once in a fresh
checkout before quoting figures (the first run compiles them inside the steps it times).

The flow runs steps in Prefect worker threads, which cProfile does not follow; this script runs
the flow's own step functions (`embody.tasks.stages`, through `tasks.execute.run_batch` with the
default config, collision depth check included) in one thread, in run order, on the first N
sequences of the default synthetic set, and prints
  * wall seconds per step and sequence (collide, retarget, refine, render, metrics), and
  * inside those, the cumulative seconds of the kernels that matter: FK, IK Jacobians, the
    self-collision proxies, the banded solve, MuJoCo verification/validation, offscreen rendering.

`--store DIR` keeps the store between invocations; `--reuse collide` then profiles the later
steps against the stored collision results, which is how the non-collision steps were tuned.
`--only STEP ...` profiles those steps alone on the store's results of the steps before them
(which must be there: a copy of a finished run's store) and stops after the last of them, so
one step's CPU can be compared before and after a change on the same stored inputs.

    python benchmarks/profile_pipeline.py [--n 3] [--top 25] [--pstats out.pstats]
                                          [--store DIR --reuse collide | --only STEP ...]
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import tempfile
import time
from collections import defaultdict
from pathlib import Path

#: (label, file suffix, function name) of the kernels reported from the profile.
KERNELS = [
    ("fk.forward", "embody/robot/fk.py", "forward"),
    ("ik.residuals", "embody/retarget/costs.py", "lazy"),
    ("ik.jacobian", "embody/retarget/costs.py", "_jacobian"),
    ("ik.collision_proxies", "embody/retarget/costs.py", "_collision"),
    ("ik.banded_solve", "embody/retarget/banded.py", "block_pentadiagonal_solve"),
    ("ik.solve", "embody/retarget/ik.py", "solve"),
    ("ik.build_targets", "embody/retarget/targets.py", "build_targets"),
    ("ik.finger_clearance", "embody/retarget/finger_clearance.py", "clear_fingers"),
    ("ik.contact_phase", "embody/retarget/ik.py", "resolve_contacts_checked"),
    ("ik.finish_solution", "embody/retarget/ik.py", "finish_solution"),
    ("ik.bridge_contacts", "embody/retarget/control.py", "bridge_contacts_checked"),
    ("ik.contact_repair", "embody/retarget/control.py", "separate_checked"),
    ("mujoco.counted_contacts", "embody/robot/contacts.py", "counted_contacts"),
    ("ik.control_trajectory", "embody/retarget/control.py", "control_trajectory_checked"),
    ("ik.kinematic_control", "embody/retarget/control.py", "_kinematic_control"),
    ("ik.dynamics_limits", "embody/retarget/dynamics_limits.py", "retime_dynamics"),
    ("mujoco.validation_counts", "embody/retarget/validation.py", "validation_counts"),
    ("critic.refine", "embody/critic/refine.py", "refine"),
    ("critic.judge", "embody/critic/refine.py", "__call__"),
    ("metrics.fidelity", "tasks/stages.py", "_fidelity"),
    ("fidelity.human_track", "embody/metrics/embodiments.py", "human_track"),
    ("fidelity.robot_track", "embody/metrics/embodiments.py", "robot_track"),
    ("fidelity.compare_with", "embody/metrics/fidelity.py", "compare_with"),
    ("collision.mitigate", "embody/collision/optimize.py", "mitigate"),
    ("collision.depths", "embody/collision/depth.py", "motion_depths"),
    ("render.sequence", "embody/render/record.py", "render_sequence"),
    ("render.mjr_render", "~", "<built-in method mujoco._render.mjr_render>"),
    ("render.mjr_readPixels", "~", "<built-in method mujoco._render.mjr_readPixels>"),
    ("render.mjr_uploadMesh", "~", "<built-in method mujoco._render.mjr_uploadMesh>"),
    ("render.encode_preview", "embody/render/preview.py", "write_preview"),
    ("render.png", "embody/render/sheet.py", "png_bytes"),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=3)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--pstats", type=Path, default=None)
    parser.add_argument("--store", type=Path, default=None, help="Store folder (default: temp).")
    names = ["collide", "retarget", "refine", "render", "metrics", "physics"]
    parser.add_argument("--reuse", nargs="*", default=[], choices=names,
                        help="Steps read from --store when already there (not profiled).")
    parser.add_argument("--only", nargs="*", default=[], choices=names,
                        help="Profile only these steps; the earlier ones are read from --store.")
    parser.add_argument("--offset", type=int, default=0, help="Skip the first N sequences.")
    parser.add_argument("--no-profile", action="store_true",
                        help="CPU seconds only, without cProfile's cost (before/after figures; "
                             "repeat in fresh processes: the steps' memos would serve a rerun).")
    args = parser.parse_args()
    if args.only:
        last = max(names.index(s) for s in args.only)
        args.reuse = [s for s in names[:last] if s not in args.only]

    from embody.config import Config
    from embody.flows.env import configure
    from embody.io import load_dataset
    from embody.synth import default_dataset
    from embody.tasks.execute import new_record, run_batch, run_shared
    from embody.tasks.pipeline import Context
    from embody.tasks.stages import default_pipeline

    store = args.store or Path(tempfile.mkdtemp(prefix="embody-prof-"))
    configure(store)
    import torch
    torch.set_num_threads(1)  # as each pipeline worker (`tasks.workers`): a second intra-op thread
    # only spins at the barriers of the steps' many small torch ops (the IK's chain FK: ~2x its CPU)
    cfg = Config.model_validate({"run": {"store": str(store), "name": "profile"}})
    data = default_dataset(store / "data")
    refs = list(load_dataset(data))[args.offset: args.offset + args.n]
    ctx = Context(cfg=cfg, store_root=str(store), run="profile")
    pipeline = default_pipeline(critic=cfg.run.critic, render=cfg.run.render)
    ctx.body, ctx.robot, ctx.critic  # noqa: B018  (per-process resources, built before timing)
    import embody.retarget  # noqa: F401

    t0 = time.perf_counter()
    shared: dict[str, str] = {}
    for step in pipeline.shared:
        rec = run_shared(step, ctx, shared)
        shared[step.name] = rec["key"]
    print(f"shared steps (once per run) {time.perf_counter() - t0:.2f} s")

    wall: dict[str, float] = defaultdict(float)
    cpu: dict[str, float] = defaultdict(float)
    prof = cProfile.Profile(time.process_time)
    records = [new_record(r) for r in refs]
    for step in pipeline.per_sequence:
        if args.only and step.name not in ("source", *args.only, *args.reuse):
            break  # past the last step asked for
        if step.name not in args.reuse:  # recompute: drop what a previous invocation stored
            for rec in records:
                if rec["status"] != "ok" or step.name == "source":
                    continue
                from embody.tasks.execute import record_key
                key, _ = record_key(step, ctx, rec, shared)
                ctx.store.remove(step.name, key)
        t, c = time.perf_counter(), time.process_time()
        profiled = step.name not in args.reuse and step.name != "source" and not args.no_profile
        if profiled:
            prof.enable()
        records = run_batch(step, ctx, records, shared)
        if profiled:
            prof.disable()
        wall[step.name] += time.perf_counter() - t
        cpu[step.name] += time.process_time() - c
        for rec in records:
            if rec["status"] != "ok":
                raise SystemExit(f"{rec['id']}: {rec['error']}\n{rec.get('traceback', '')}")

    n = len(refs)
    for step in ["source", *args.reuse]:
        wall.pop(step, None)
        cpu.pop(step, None)
    print(f"\nseconds per sequence (n={n}, one thread of steps): CPU, wall")
    for step, secs in cpu.items():
        print(f"  {step:10s} {secs / n:7.2f} {wall[step] / n:7.2f}")
    if args.no_profile:
        total = sum(cpu.values()) / n
        print("RESULT " + " ".join([f"cpu_seconds_per_seq={total:.2f}", f"load1={os.getloadavg()[0]:.1f}"]
                                   + [f"{k}_s={v / n:.2f}" for k, v in cpu.items()]))
        return
    stats = pstats.Stats(prof)
    if args.pstats:
        stats.dump_stats(args.pstats)
    cum: dict[str, float] = {}
    calls: dict[str, int] = {}
    for (file, _, func), (_, ncalls, _, ct, _) in stats.stats.items():  # type: ignore[attr-defined]
        for label, suffix, name in KERNELS:
            if file.endswith(suffix) and func == name:
                cum[label] = cum.get(label, 0.0) + ct
                calls[label] = calls.get(label, 0) + ncalls
    print("\nkernels (cumulative CPU seconds per sequence, calls per sequence):")
    for label, _, _ in KERNELS:
        if label in cum:
            print(f"  {label:26s} {cum[label] / n:7.2f} s  {calls[label] / n:8.0f} calls")
    print(f"\ntop {args.top} functions by cumulative time:")
    stats.sort_stats("cumulative").print_stats(args.top)
    total = sum(cpu.values()) / n
    print("RESULT " + " ".join([f"cpu_seconds_per_seq={total:.2f}", f"load1={os.getloadavg()[0]:.1f}"]
                               + [f"{k}_s={v / n:.2f}" for k, v in cpu.items()]
                               + [f"{k}_s={v / n:.2f}" for k, v in cum.items()]))


if __name__ == "__main__":
    main()
