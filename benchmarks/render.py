"""Render throughput at 320×240 (shadows, reflections, skybox off): robot and reference mesh.

Prints one row per (view, kind) and ends with
`RESULT robot_fps=… reference_fps=… width=320 height=240`. Target: ≥ 8 frames/s on a CPU.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from embody.body import load_body_model
from embody.config.ik import IKConfig
from embody.config.render import RenderConfig
from embody.motion import Motion
from embody.render.compare import open_renderer, reference_vertices
from embody.retarget import shape_fit
from embody.robot import load_robot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = RenderConfig(width=args.width, height=args.height, views=["front", "side"])
    robot, body = load_robot(), load_body_model()
    fit = shape_fit(robot, body, IKConfig())
    n = args.frames
    s = np.linspace(0, 1, n)
    pose = np.zeros((n, 55, 3), np.float32)
    pose[:, 16, 2], pose[:, 17, 2] = -1.0 + 0.4 * s, 1.0 - 0.4 * s
    pose[:, 18, 1], pose[:, 19, 1] = -1.9, 1.9
    motion = Motion(pose=pose, transl=np.zeros((n, 3)), betas=np.zeros(10), fps=30.0)
    verts = reference_vertices(motion, body, fit, np.arange(n))
    q = np.tile(robot.tpose, (n, 1))
    for side, sign in (("left", 1), ("right", -1)):
        q[:, robot.joint_index(f"{side}_shoulder_roll_joint")] = sign * (0.3 + 1.0 * s)
        q[:, robot.joint_index(f"{side}_elbow_joint")] = 1.0 * s
    fps: dict[str, list[float]] = {"robot": [], "reference": []}
    background = np.round(np.asarray(cfg.background_rgb) * 255)
    with open_renderer(robot, body, fit, cfg) as renderer:
        renderer.robot_frames(q[:2])  # warm-up: first draws compile shaders
        renderer.reference_frames(verts[:2])
        for view in cfg.views:
            for kind, fn, data in (("robot", renderer.robot_frames, q),
                                   ("reference", renderer.reference_frames, verts)):
                t0 = time.perf_counter()
                frames = fn(data, view)
                dt = time.perf_counter() - t0
                fps[kind].append(n / dt)
                print(f"view={view:5s} kind={kind:9s} frames={len(frames)} seconds={dt:.2f} "
                      f"fps={n / dt:.1f} foreground="
                      f"{float((np.abs(frames - background).max(-1) > 0).mean()):.3f}")
    print(f"RESULT robot_fps={np.mean(fps['robot']):.1f} reference_fps={np.mean(fps['reference']):.1f} "
          f"width={args.width} height={args.height}")


if __name__ == "__main__":
    main()
