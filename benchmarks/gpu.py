"""The torch paths on CUDA against the CPU, both measured in this run on this machine.

Rows (best of 3 after a warm-up, `torch.cuda.synchronize()` around each CUDA call; the CPU
side on one thread, as the pipeline's workers run it):

- `skin`: body skinning (`MannequinBody.vertices`) of `--frames` frames, forward + backward;
- `energy`: the collision energy of a colliding default sequence (`frame_energies`, contact
  stride, every frame) and its gradient in the pose;
- `fk_<n>`: pytorch-kinematics FK of the default robot's IK bodies for n configurations,
  forward + backward;
- `mitigate`: `collision.mitigate` of `--n` default sequences with `device: cpu` and
  `device: cuda` (the same configuration otherwise): the optimiser's seconds per 150 frames
  (the mesh judge, CPU-only in both, kept apart as `judge`), and what each gives (Pose MSE,
  mesh depth after) so the two can be compared for quality, not only speed. Before each
  device's timed sequences, `mitigate` runs once untimed on a short colliding window
  (`benchmarks/collision.py`'s `warm_up`): a fresh process compiles or loads the CPU kernels
  (numba) and CUDA's first-call kernels there, a start-up cost, not a per-150-frame one.

Prints one row per item and ends with `RESULT gpu=<name> ...` (speedups are CPU time / CUDA
time). Without a CUDA device it says so and exits 2. Run:

    PYTHONPATH=. python benchmarks/gpu.py [--n 4] [--frames 150] [--data DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from embody.body import MannequinBody
from embody.collision import mitigate
from embody.collision.energy import collision_model, frame_energies
from embody.config import load_config
from embody.io import load
from embody.robot import load_robot
from embody.synth import default_dataset

from benchmarks.collision import warm_up

ROOT = Path(__file__).resolve().parents[1]
REPEATS = 3


def best_of(fn: Callable[[], object], cuda: bool) -> float:
    """Best wall time (s) of REPEATS calls after one warm-up."""
    fn()
    times = []
    for _ in range(REPEATS):
        if cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return min(times)


def skin_row(body: MannequinBody, pose: np.ndarray, betas: np.ndarray,
             dev: torch.device) -> float:
    p = torch.as_tensor(pose, dtype=torch.float32, device=dev)
    b = torch.as_tensor(betas, dtype=torch.float32, device=dev)

    def run() -> None:
        q = p.clone().requires_grad_()
        body.vertices(q, b).square().sum().backward()
    return best_of(run, dev.type == "cuda")


def energy_row(body: MannequinBody, pose: np.ndarray, betas: np.ndarray, stride: int,
               dev: torch.device) -> tuple[float, float]:
    model = collision_model(body, betas, vertex_stride=stride)
    p = torch.as_tensor(pose, dtype=torch.float32, device=dev)
    b = torch.as_tensor(betas, dtype=torch.float32, device=dev)
    value = [0.0]

    def run() -> None:
        q = p.clone().requires_grad_()
        e = frame_energies(model, body.joint_transforms(q, b)).sum()
        e.backward()
        value[0] = float(e.detach())
    return best_of(run, dev.type == "cuda"), value[0]


def fk_row(robot, n: int, dev: torch.device) -> float:
    bodies = [robot.spec.links[k].body for k in robot.spec.links]
    rng = np.random.default_rng(0)
    lo, hi = robot.lower, robot.upper
    q0 = torch.as_tensor(rng.uniform(lo, hi, size=(n, len(lo))), dtype=torch.float64, device=dev)

    def run() -> None:
        q = q0.clone().requires_grad_()
        robot.body_transforms(q, bodies)[..., :3, 3].square().sum().backward()
    return best_of(run, dev.type == "cuda")


def mitigate_row(paths: list[Path], body: MannequinBody, device: str) -> dict[str, float]:
    cfg = load_config().collision.model_copy(update={"device": device})
    warm_up(paths[0], body, cfg)
    opt_s = judge_s = frames = 0.0
    mse, depth = [], []
    for p in paths:
        motion = load(p)
        m = mitigate(motion, body, cfg).metrics
        opt_s += m["runtime_s"]
        judge_s += m.get("depth_s", 0.0)
        frames += m["frames"]
        mse.append(m["pose_mse"])
        depth.append(m.get("max_depth_mm_after", float("nan")))
    return {"opt_s_per_150": opt_s / frames * 150, "judge_s_per_150": judge_s / frames * 150,
            "pose_mse_median": float(np.median(mse)), "max_depth_mm_after": float(np.max(depth))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4, help="default sequences to mitigate")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--data", default=str(ROOT / "data"))
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print(f"no CUDA device (torch {torch.__version__}): nothing to compare", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    cpu, gpu = torch.device("cpu"), torch.device("cuda")
    name = torch.cuda.get_device_name(0)
    print(f"GPU: {name}; torch {torch.__version__}; CUDA {torch.version.cuda}", flush=True)
    paths = sorted(default_dataset(args.data).glob("seq_*.npz"))[: args.n]
    body = MannequinBody()
    motion = load(paths[0])
    pose = np.resize(motion.pose, (args.frames, *motion.pose.shape[1:]))
    stride = load_config().collision.contact_stride
    out: dict[str, float] = {}

    s_cpu, s_gpu = skin_row(body, pose, motion.betas, cpu), skin_row(body, pose, motion.betas, gpu)
    print(f"skin {args.frames} frames fwd+bwd: cpu {s_cpu * 1e3:.1f} ms  cuda {s_gpu * 1e3:.1f} ms",
          flush=True)
    out["skin_speedup"] = s_cpu / s_gpu

    (e_cpu, v_cpu), (e_gpu, v_gpu) = (energy_row(body, pose, motion.betas, stride, d)
                                      for d in (cpu, gpu))
    print(f"energy+grad {args.frames} frames: cpu {e_cpu * 1e3:.1f} ms  cuda {e_gpu * 1e3:.1f} ms"
          f"  (energy {v_cpu:.6g} vs {v_gpu:.6g})", flush=True)
    out["energy_speedup"] = e_cpu / e_gpu
    out["energy_rel_diff"] = abs(v_cpu - v_gpu) / max(abs(v_cpu), 1e-12)

    robot = load_robot(load_config().robot)
    for n in (args.frames, 4096):
        f_cpu, f_gpu = fk_row(robot, n, cpu), fk_row(robot, n, gpu)
        print(f"pk FK fwd+bwd {n} configs: cpu {f_cpu * 1e3:.1f} ms  cuda {f_gpu * 1e3:.1f} ms",
              flush=True)
        out[f"fk{n}_speedup"] = f_cpu / f_gpu

    for device in ("cpu", "cuda"):
        r = mitigate_row(paths, body, device)
        print(f"mitigate {len(paths)} seqs device={device}: optimiser {r['opt_s_per_150']:.2f} s "
              f"per 150 frames, judge {r['judge_s_per_150']:.2f} s, Pose MSE median "
              f"{r['pose_mse_median']:.4f}, max depth after {r['max_depth_mm_after']:.2f} mm",
              flush=True)
        for k, v in r.items():
            out[f"{device}_{k}"] = v
    out["mitigate_speedup"] = out["cpu_opt_s_per_150"] / out["cuda_opt_s_per_150"]
    fields = " ".join(f"{k}={v:.4g}" for k, v in out.items())
    print(f"RESULT gpu={name.replace(' ', '_')} n={len(paths)} {fields}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
