"""The render step alone: `render_sequence` (comparison sheet + preview) on the default set.

Renders the first N sequences of the default synthetic set (the source motion as reference, the
robot signing it: IK on the source motion, not timed; `--tpose`: a slowly waving T-pose, as
before the preview was cropped to what the bodies reach) exactly as the pipeline's render step
does, and reports wall and CPU seconds per sequence (CPU time of every thread of the process,
llvmpipe's included, plus the x264 encoder child's, `render_child_cpu_s` alone: the steadier
figure on a shared machine; `render_cpu_s_warm` leaves out the first sequence, which also
prepares the robot model once a process), the CPU milliseconds per drawn image (reference and
robot of every preview frame and first-view keyframe, plus the other views' keyframes; the
encoder and sheet included), the preview's frame count, size and bytes. Run it on two checkouts
back to back (`PYTHONPATH=<checkout>`) to compare.

    python benchmarks/render_step.py [--n 3] [--phases] [--tpose]
"""

from __future__ import annotations

import argparse
import io
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def _preview_shape(blob: bytes, suffix: str) -> tuple[int, int, int]:
    """(frames, height, width) of a stored preview."""
    if suffix == ".mp4":
        import imageio_ffmpeg
        with tempfile.NamedTemporaryFile(suffix=".mp4") as f:
            f.write(blob)
            f.flush()
            reader = imageio_ffmpeg.read_frames(f.name)
            meta = next(reader)
            frames = sum(1 for _ in reader)
            w, h = meta["size"]
            return frames, h, w
    from PIL import Image
    img = Image.open(io.BytesIO(blob))
    return img.n_frames, img.size[1], img.size[0]


def _cpu() -> float:
    """CPU seconds of this process (all its threads: llvmpipe's too) and its finished
    children (the ffmpeg encoder)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _child_cpu() -> float:
    """CPU seconds of this process's finished children (the ffmpeg encoder) alone."""
    t = os.times()
    return t.children_user + t.children_system


def phases(motion, body, fit, robot, q: np.ndarray, keys: np.ndarray, cfg) -> dict[str, float]:
    """CPU ms per preview frame of each phase of one `render_sequence` call, each timed
    exclusive of the phases it calls: opening the renderer, the preview's crop, reference and
    robot images (the preview's pass and the other views' keyframes), the x264 encoder (the
    child's CPU, at close), the sheet PNG, closing the renderer, and the rest."""
    from embody.render import compare, record, scene
    from embody.render.preview import PreviewWriter
    acc: dict[str, float] = {}
    stack: list[float] = []  # CPU time of the phases called inside the running one

    def wrap(owner, attr, name):
        fn = getattr(owner, attr)

        def timed(*a, **k):
            c = _cpu()
            stack.append(0.0)
            try:
                return fn(*a, **k)
            finally:
                inner = stack.pop()
                spent = _cpu() - c
                acc[name] = acc.get(name, 0.0) + spent - inner
                if stack:
                    stack[-1] += spent
        setattr(owner, attr, timed)
        return owner, attr, fn

    patched = [wrap(record, "open_renderer", "open_renderer"),
               wrap(compare, "preview_crop", "crop"),
               wrap(compare, "draw_reference", "reference_image"),
               wrap(scene.SceneRenderer, "robot_frames", "robot_image"),
               wrap(PreviewWriter, "add", "encode"), wrap(PreviewWriter, "close", "encode"),
               wrap(compare.Comparison, "sheet_png", "sheet_png"),
               wrap(scene.SceneRenderer, "close", "close")]
    try:
        c = _cpu()
        record.render_sequence(motion, body, fit, robot, q, keys, cfg, "bench")
        total = _cpu() - c
    finally:
        for owner, attr, fn in patched:
            setattr(owner, attr, fn)
    acc["other"] = total - sum(acc.values())
    shown = len(compare.preview_frames(cfg, len(q), motion.fps)[0])
    return {k: 1000 * v / shown for k, v in acc.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=3)
    parser.add_argument("--tpose", action="store_true",
                        help="The robot at a slowly waving T-pose (the figures before "
                             "2026-11-27 s14) instead of IK on the motion.")
    parser.add_argument("--phases", action="store_true",
                        help="Also print CPU ms per preview frame of each drawing phase.")
    args = parser.parse_args()
    import torch
    torch.set_num_threads(1)
    from embody.body import load_body_model
    from embody.config import Config
    from embody.io import load_dataset
    from embody.render.compare import preview_frames
    from embody.render.record import render_sequence
    from embody.retarget import shape_fit
    from embody.robot import load_robot
    from embody.synth import default_dataset

    cfg = Config()
    data = default_dataset(Path(tempfile.mkdtemp(prefix="embody-render-")))
    motions = [r.load() for r in list(load_dataset(data))[: args.n]]
    body, robot = load_body_model(cfg.body), load_robot(cfg.robot)
    fit = shape_fit(robot, body, cfg.ik)
    roll = robot.joint_index("left_shoulder_roll_joint")
    from embody.render import select_keyframes
    from embody.retarget import build_targets
    from embody.retarget.windows import solve_windowed
    walls, cpus, children, drawn = [], [], [], []
    for motion in motions:
        t = motion.num_frames
        if args.tpose:
            q = np.tile(robot.tpose, (t, 1))
            q[:, roll] += 0.5 * np.sin(np.linspace(0, 2 * np.pi, t))
            keys = np.linspace(0, t - 1, cfg.render.keyframes).round().astype(np.int64)
        else:  # the robot signing (IK on the source motion) and the step's keyframes
            targets = build_targets(motion, body, fit, robot, cfg.ik)
            q = solve_windowed(robot, targets, cfg.ik).q
            keys = select_keyframes(targets.wrist_pos, cfg.render.keyframes)
        w0, c0, k0 = time.perf_counter(), _cpu(), _child_cpu()
        out = render_sequence(motion, body, fit, robot, q, keys, cfg.render, "bench")
        walls.append(time.perf_counter() - w0)
        cpus.append(_cpu() - c0)
        children.append(_child_cpu() - k0)
        shape = _preview_shape(out.preview, out.preview_suffix) if out.preview else (0, 0, 0)
        # images drawn: reference + robot per preview frame or keyframe (first view), and per
        # keyframe of the other views
        shown = (preview_frames(cfg.render, t, motion.fps)[0] if out.preview
                 else np.zeros(0, np.int64))
        drawn.append(2 * len(np.union1d(shown, keys)) * (len(cfg.render.views) > 0)
                     + 2 * len(keys) * (len(cfg.render.views) - 1))
        print(f"frames={t} fps={motion.fps:g} wall_s={walls[-1]:.2f} cpu_s={cpus[-1]:.2f} "
              f"child_cpu_s={children[-1]:.2f} "
              f"cpu_ms_per_image={1000 * cpus[-1] / drawn[-1]:.1f} "
              f"preview_frames={shape[0]} preview_hw={shape[1]}x{shape[2]} "
              f"preview_kb={len(out.preview or b'') / 1024:.0f} sheet_kb={len(out.sheet_png) / 1024:.0f}")
    if args.phases:
        split = phases(motions[-1], body, fit, robot, q, keys, cfg.render)
        print("phases (CPU ms per preview frame): "
              + " ".join(f"{k}={v:.1f}" for k, v in split.items()))
    # the first sequence also prepares the robot model and compiles GL state, once a process
    warm = np.mean(cpus[1:]) if len(cpus) > 1 else cpus[0]
    print(f"RESULT render_s={np.mean(walls):.2f} render_cpu_s={np.mean(cpus):.2f} "
          f"render_cpu_s_warm={warm:.2f} render_child_cpu_s={np.mean(children):.2f} "
          f"cpu_ms_per_image={1000 * np.sum(cpus) / np.sum(drawn):.1f} "
          f"preview_frames={shape[0]} preview_height={shape[1]} preview_width={shape[2]} "
          f"sequences={len(motions)}")


if __name__ == "__main__":
    main()
