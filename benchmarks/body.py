"""Body-model throughput on a 150-frame sequence: torch MannequinBody vs mannequin-x NumPy.

Prints one row per item, then `RESULT ...`. Run: python benchmarks/body.py
"""

from __future__ import annotations

import time

import numpy as np
import torch
from mannequin import Mannequin

from embody.body import MannequinBody

FRAMES = 150
REPEATS = 3


def best_of(fn) -> float:
    """Best wall time of REPEATS runs (after one warm-up), in seconds."""
    fn()
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    pose = (rng.normal(size=(FRAMES, 55, 3)) * 0.4).astype(np.float32)
    betas = rng.normal(size=10).astype(np.float32)
    transl = rng.normal(size=(FRAMES, 3)).astype(np.float32)
    body = MannequinBody()
    ref = Mannequin("wooden", shape=betas, flat_hand_mean=True)
    params = dict(body_pose=pose[:, 1:22], head_pose=pose[:, 22:25], hand_pose=pose[:, 25:],
                  pelvis_rotation=pose[:, 0], global_translation=transl,
                  shape=np.broadcast_to(betas, (FRAMES, 10)))
    p, b, t = (torch.tensor(a) for a in (pose, betas, transl))

    def joints_backward() -> None:
        q = p.clone().requires_grad_()
        body.joints(q, b, t).square().sum().backward()

    def vertices_backward() -> None:
        q = p.clone().requires_grad_()
        body.vertices(q, b, t).square().sum().backward()

    rows = {
        "numpy_vertices": best_of(lambda: ref.vertices(params)),
        "torch_vertices": best_of(lambda: body.vertices(p, b, t)),
        "numpy_joints": best_of(lambda: ref.joint_transforms(params)),
        "torch_joints": best_of(lambda: body.joints(p, b, t)),
        "torch_joints_fwd_bwd": best_of(joints_backward),
        "torch_vertices_fwd_bwd": best_of(vertices_backward),
    }
    err = np.abs(body.vertices(p, b, t).numpy() - ref.vertices(params)).max()
    for name, seconds in rows.items():
        print(f"{name:24s} {seconds * 1e3:9.1f} ms  {FRAMES / seconds:9.0f} frames/s")
    print(f"{'max_vertex_error':24s} {err:.2e} m")
    print(f"RESULT frames={FRAMES} torch_vertices_fps={FRAMES / rows['torch_vertices']:.0f} "
          f"numpy_vertices_fps={FRAMES / rows['numpy_vertices']:.0f} "
          f"torch_joints_fps={FRAMES / rows['torch_joints']:.0f} "
          f"vertices_fwd_bwd_ms={rows['torch_vertices_fwd_bwd'] * 1e3:.0f} "
          f"max_vertex_error_m={err:.1e}")


if __name__ == "__main__":
    main()
