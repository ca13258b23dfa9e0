"""The whole collide step (`mitigate_windowed`: optimiser, mesh judge before/after, polish,
pull-back) over the default dataset in one process, one torch and one BLAS thread (as a
pipeline worker runs it): CPU seconds per sequence, the judge's share, and one digest of every
array and metric the step stores (timings left out).

Why: `benchmarks/collision_cpu.py` takes the judge out, and the pipeline's figure mixes in
the other steps and the machine's load; this is the step's CPU alone. Equal digests between
two checkouts mean the same step output bit for bit. To compare, run it with each checkout on
PYTHONPATH back to back (alternating). One untimed sequence loads the compiled kernels first
(numba's cache: a per-process cost); the judge's memo is cleared after it. Ends with one
`RESULT` line.

    PYTHONPATH=<checkout> python benchmarks/collide_cpu.py [--data DIR] [--n 24]
"""

from __future__ import annotations

import hashlib
import time

import numpy as np
from threadpoolctl import threadpool_limits

from _collide_cpu import prepare, time_judge
from embody.collision.windows import mitigate_windowed
from embody.device import torch_threads
from embody.io import load


def main() -> None:
    with threadpool_limits(1), torch_threads(1):
        paths, body, cfg = prepare(mitigate_windowed, __doc__.splitlines()[0])
        judge_cpu = time_judge("_mesh_depths")
        motions = [load(p) for p in paths]
        digest = hashlib.sha256()
        cpu = 0.0
        for m in motions:
            c = time.process_time()
            r = mitigate_windowed(m, body, cfg)
            cpu += time.process_time() - c
            for k, v in sorted(r.to_arrays().items()):
                digest.update(k.encode() + np.ascontiguousarray(v).tobytes())
            digest.update(repr(sorted((k, v) for k, v in r.metrics.items()
                                      if not k.endswith("_s"))).encode())
    n = len(motions)
    print(f"RESULT sequences={n} collide_cpu_s_per_seq={cpu / n:.3f} "
          f"judge_cpu_s_per_seq={judge_cpu[0] / n:.3f} "
          f"rest_cpu_s_per_seq={(cpu - judge_cpu[0]) / n:.3f} "
          f"output_sha256={digest.hexdigest()[:16]}")


if __name__ == "__main__":
    main()
