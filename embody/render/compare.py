"""Reference-vs-robot renders of one sequence: keyframe images, the sheet and the preview.

The reference body is posed with the fitted shape, its root rotation removed and mapped through
the shape fit into the robot torso frame: exactly how the retargeting targets are built, so the
human wrists in the images are the IK's reference wrists.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from embody.body.base import BodyModel
from embody.config.render import RenderConfig
from embody.motion import Motion
from embody.render.preview import write_preview
from embody.render.scene import SceneRenderer
from embody.render.sheet import comparison_sheet, png_bytes


def reference_vertices(motion: Motion, body: BodyModel, fit, frames: np.ndarray) -> np.ndarray:
    """Body mesh vertices (N,V,3) at `frames`, in the robot torso frame (as `build_targets`)."""
    pose = torch.as_tensor(motion.pose[frames], dtype=torch.float64).clone()
    pose[:, 0] = 0.0
    betas = torch.as_tensor(fit.betas, dtype=torch.float64)
    with torch.no_grad():
        verts = body.vertices(pose, betas)
        return fit.apply(verts).cpu().numpy()


def open_renderer(robot, body: BodyModel, fit, cfg: RenderConfig) -> SceneRenderer:
    """A renderer for this robot with the fitted body as reference mesh."""
    with torch.no_grad():
        betas = torch.as_tensor(fit.betas, dtype=torch.float64)
        rest = body.rest_vertices(betas)
        points = fit.apply(body.vertices(reach_poses(), betas)).cpu().numpy().reshape(-1, 3)
    return SceneRenderer(robot, cfg, np.asarray(body.faces), rest.cpu().numpy(),
                         torso_body=robot.spec.torso_body, reference_points=points)


def reach_poses() -> torch.Tensor:
    """Body poses (4,55,3) spanning the arms' reach: T-pose, arms up, arms forward, arms folded
    across the chest. The framing holds the fitted body in all of them (and the robot's reach)."""
    pose = torch.zeros((4, 55, 3), dtype=torch.float64)
    left, right = 16, 17  # SMPL-X shoulders; y-up body frame, the left arm along +x
    pose[1, left, 2], pose[1, right, 2] = np.pi / 2, -np.pi / 2    # about z: arms up
    pose[2, left, 1], pose[2, right, 1] = -np.pi / 2, np.pi / 2    # about y: arms forward
    pose[3, left, 1], pose[3, right, 1] = -np.pi * 0.8, np.pi * 0.8  # across the chest
    return pose


@dataclass
class Comparison:
    """Keyframe renders per view: reference and robot (K,H,W,3) each."""

    keyframes: np.ndarray
    fps: float
    reference: dict[str, np.ndarray] = field(default_factory=dict)
    robot: dict[str, np.ndarray] = field(default_factory=dict)

    def sheet_png(self, title: str = "") -> bytes:
        rows: list[tuple[str, np.ndarray]] = []
        for view in self.reference:
            rows += [(f"human {view}", self.reference[view]), (f"robot {view}", self.robot[view])]
        labels = [f"f{k} {k / self.fps:.2f}s" for k in self.keyframes]
        return png_bytes(comparison_sheet(rows, labels, title))

    def keyframe_pngs(self) -> list[bytes]:
        """One PNG per keyframe: reference over robot, first view."""
        view = next(iter(self.reference))
        return [png_bytes(np.concatenate([self.reference[view][i], self.robot[view][i]], axis=0))
                for i in range(len(self.keyframes))]


def render_comparison(renderer: SceneRenderer, cfg: RenderConfig, keyframes: np.ndarray,
                      fps: float, q: np.ndarray, reference: dict[str, np.ndarray] | None = None,
                      reference_verts: np.ndarray | None = None) -> Comparison:
    """Render robot keyframes (and the reference ones unless given, from `reference_verts`)."""
    comp = Comparison(np.asarray(keyframes), fps)
    for view in cfg.views:
        comp.robot[view] = renderer.robot_frames(q[keyframes], view)
        comp.reference[view] = (reference[view] if reference is not None
                                else renderer.reference_frames(reference_verts, view))
    return comp


def render_preview(renderer: SceneRenderer, cfg: RenderConfig, motion: Motion, body: BodyModel,
                   fit, q: np.ndarray, path: Path) -> Path | None:
    """Side-by-side reference | robot animation of (subsampled) frames, first view."""
    if cfg.preview_format == "none":
        return None
    num_frames = len(q)
    duration = num_frames / motion.fps
    count = int(np.clip(round(duration * cfg.preview_fps), 2, min(cfg.preview_max_frames, num_frames)))
    frames = np.unique(np.linspace(0, num_frames - 1, count).round().astype(np.int64))
    view = cfg.views[0]
    ref = renderer.reference_frames(reference_vertices(motion, body, fit, frames), view)
    rob = renderer.robot_frames(q[frames], view)
    # real-time playback of the subsampled frames
    return write_preview(np.concatenate([ref, rob], axis=2), path, len(frames) / duration,
                         cfg.preview_format)
