"""A/B of the IK's sphere/hull proxy contacts: compiled (`proxy_hulls.hull_contacts`) vs the NumPy
reference (`hull_contacts_numpy`), in one process, single-threaded, process CPU time.

Input: the 4 sequences of `benchmarks/ik_vs_mink.py` (mitigated, plain shape-fit targets), built
once and pickled to `--targets` (mitigation is ~15 s a sequence). For each round and sequence the
whole `solve` runs with each query (order alternating), timing `Residuals._collision` inside it;
then the two solutions are compared (max |dq|, wrist error, jerk, collision frames).

Usage: python benchmarks/ik_proxy_hulls.py [--targets PATH] [--rounds 2]
"""

from __future__ import annotations

import argparse
import os
import pickle
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from embody.config import Config  # noqa: E402
from embody.retarget import costs  # noqa: E402
from embody.retarget.proxy_hulls import hull_contacts, hull_contacts_numpy  # noqa: E402
from embody.robot import load_robot  # noqa: E402


def load_targets(path: Path, config: Config, robot, n: int) -> list:
    """The benchmark's targets (`ik_vs_mink.py`'s input), cached at `path`."""
    if path.exists():
        return pickle.loads(path.read_bytes())[:n]
    from embody.body import load_body_model
    from embody.collision import mitigate
    from embody.retarget import build_targets, shape_fit
    from embody.synth import generate_sequence
    body = load_body_model(config.body)
    fit = shape_fit(robot, body, config.ik)
    seqs = [mitigate(generate_sequence(0, i), body, config.collision).motion for i in range(n)]
    targets = [build_targets(m, body, fit, robot) for m in seqs]
    path.write_bytes(pickle.dumps(targets))
    return targets


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--targets", type=Path, default=Path("/tmp/ik_vs_mink_targets.pkl"))
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(1)
    config = Config()
    robot = load_robot(config.robot)
    targets = load_targets(args.targets, config, robot, args.sequences)
    from embody.retarget import solve
    queries = {"numpy": hull_contacts_numpy, "numba": hull_contacts}
    res = costs.Residuals(robot, targets[0], config.ik)
    rot, pos = res.fk.forward(np.tile(robot.rest, (2, 1)))
    t0 = time.perf_counter()
    hull_contacts(res.hulls, rot, pos, config.ik.collision_margin)
    first_call_s = time.perf_counter() - t0  # the kernel's first call: numba's cache load (or compile)
    solve(robot, targets[0], config.ik.model_copy(update={"iterations": 1}))  # warm up
    original = costs.Residuals._collision
    spent = {k: [0.0, 0] for k in queries}
    solve_s = {k: 0.0 for k in queries}
    sols: dict[str, list] = {k: [None] * len(targets) for k in queries}
    try:
        for rnd in range(args.rounds):
            for i, tg in enumerate(targets):
                for name in (list(queries) if (rnd + i) % 2 == 0 else list(queries)[::-1]):
                    def timed(self, rot, pos, scale=1.0, hulls=None, _q=queries[name], _n=name):
                        c0 = time.process_time()
                        out = original(self, rot, pos, scale, hulls or _q)
                        spent[_n][0] += time.process_time() - c0
                        spent[_n][1] += 1
                        return out
                    costs.Residuals._collision = timed
                    c0 = time.process_time()
                    sol = solve(robot, tg, config.ik)
                    solve_s[name] += time.process_time() - c0
                    sols[name][i] = sol
    finally:
        costs.Residuals._collision = original
    dq = max(float(np.abs(a.q - b.q).max()) for a, b in zip(sols["numpy"], sols["numba"]))
    for i, (a, b) in enumerate(zip(sols["numpy"], sols["numba"])):
        print(f"seq {i}: max|dq| {np.abs(a.q - b.q).max():.2e}", *(
            f"{k} {a.metrics[k]:.6f}/{b.metrics[k]:.6f}" for k in ("wrist_pos_err_mm", "jerk", "self_collision_frames")))
    ms = {k: 1000 * s / max(n, 1) for k, (s, n) in spent.items()}
    same = all(a.metrics[k] == b.metrics[k] for a, b in zip(sols["numpy"], sols["numba"])
               for k in ("self_collision_frames",))
    print(f"RESULT collision_ms_numpy={ms['numpy']:.3f} collision_ms_numba={ms['numba']:.3f} "
          f"collision_speedup={ms['numpy'] / ms['numba']:.2f} calls={spent['numba'][1]} "
          f"solve_cpu_s_numpy={solve_s['numpy'] / args.rounds:.3f} solve_cpu_s_numba={solve_s['numba'] / args.rounds:.3f} "
          f"solve_speedup={solve_s['numpy'] / solve_s['numba']:.3f} max_dq={dq:.2e} "
          f"same_collision_frames={int(same)} first_call_s={first_call_s:.2f}")


if __name__ == "__main__":
    main()
