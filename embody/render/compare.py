"""Reference-vs-robot renders of one sequence: keyframe images, the sheet and the preview.

The reference body is posed with the fitted shape, its root rotation removed and mapped through
the shape fit into the robot torso frame: exactly how the retargeting targets are built, so the
human wrists in the images are the IK's reference wrists.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse
import torch

from embody.body.base import BodyModel
from embody.config.render import RenderConfig
from embody.motion import Motion
from embody.render.preview import PreviewWriter
from embody.render.scene import Crop, SceneRenderer, downsample, is_similarity
from embody.render.sheet import comparison_sheet, png_bytes

#: Frames skinned at once for the preview (bounds memory on long sequences).
_CHUNK = 32
#: Pixels kept around what the bodies reach in a cropped preview (`preview_crop`).
_CROP_MARGIN = 4


def _root_free(motion: Motion, frames: np.ndarray) -> torch.Tensor:
    pose = torch.as_tensor(np.asarray(motion.pose)[frames], dtype=torch.float64).clone()
    pose[:, 0] = 0.0
    return pose


def reference_vertices(motion: Motion, body: BodyModel, fit, frames: np.ndarray) -> np.ndarray:
    """Body mesh vertices (N,V,3) at `frames`, in the robot torso frame (as `build_targets`)."""
    betas = torch.as_tensor(fit.betas, dtype=torch.float64)
    with torch.no_grad():
        verts = body.vertices(_root_free(motion, frames), betas)
        return fit.apply(verts).cpu().numpy()


class ReferenceSkin:
    """Vertices of only the drawn (decimated) reference mesh, in the torso frame: linear blend
    skinning of those vertices in float32 (images need no more) with the weights as a sparse
    matrix (at most 4 bones a vertex here: ~10× fewer products than the dense blend), when it
    reproduces `body.vertices` to 10 µm (checked on the reach poses; a body with
    pose-dependent shape falls back to skinning every vertex)."""

    def __init__(self, body: BodyModel, fit, keep: np.ndarray, check_poses: torch.Tensor,
                 check_vertices: torch.Tensor) -> None:
        self.body, self.fit, self.keep = body, fit, np.asarray(keep)
        self.betas = torch.as_tensor(fit.betas, dtype=torch.float64)
        with torch.no_grad():
            self.rest = body.rest_vertices(self.betas)[self.keep].cpu().numpy().astype(np.float32)
            self.bind = body.rest_joints(self.betas).cpu().numpy().astype(np.float32)
            self.weights = scipy.sparse.csr_matrix(
                np.asarray(body.skin_weights)[self.keep].astype(np.float32))
            own = self._skin(body.joint_transforms(check_poses, self.betas))
            self.exact = bool(np.abs(own - check_vertices[:, self.keep].cpu().numpy()).max() < 1e-5)

    def _skin(self, transforms: torch.Tensor) -> np.ndarray:
        """v = Σ_j w_vj (R_j (v_rest − b_j) + t_j), as `body.kinematics.skin`, (T,K,3) float64."""
        tf = transforms.cpu().numpy().astype(np.float32)  # (T,J,4,4)
        rot = tf[..., :3, :3]
        trans = tf[..., :3, 3] - np.einsum("tjab,jb->tja", rot, self.bind)
        bone = np.concatenate([rot, trans[..., None]], axis=-1)  # (T,J,3,4)
        t, j = bone.shape[:2]
        blended = (self.weights @ bone.transpose(1, 0, 2, 3).reshape(j, -1)).reshape(-1, t, 3, 4)
        out = np.einsum("vtab,vb->tva", blended[..., :3], self.rest) + blended[..., 3].transpose(1, 0, 2)
        return out.astype(np.float64)

    def transforms(self, motion: Motion, frames: np.ndarray) -> np.ndarray:
        """(N,J,4,4) body-frame joint transforms at `frames` (root rotation removed): what a
        renderer's bound skin (`SceneRenderer.bind_reference_skin`) draws from."""
        with torch.no_grad():
            return self.body.joint_transforms(_root_free(motion, np.asarray(frames)),
                                              self.betas).cpu().numpy()

    def __call__(self, motion: Motion, frames: np.ndarray) -> np.ndarray:
        """(N,K,3) torso-frame vertices of the drawn mesh at `frames`."""
        frames = np.asarray(frames)
        out = []
        with torch.no_grad():
            for start in range(0, len(frames), _CHUNK):
                pose = _root_free(motion, frames[start:start + _CHUNK])
                if self.exact:
                    verts = torch.from_numpy(self._skin(self.body.joint_transforms(pose, self.betas)))
                else:
                    verts = self.body.vertices(pose, self.betas)[:, self.keep]
                out.append(self.fit.apply(verts).cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, len(self.keep), 3))


def _subtree_bones(body: BodyModel, roots: tuple[str, ...]) -> np.ndarray:
    names = list(body.joint_names)
    parents = np.asarray(body.parents)
    inside = np.zeros(len(names), dtype=bool)
    for j in range(len(names)):  # parents precede children
        inside[j] = names[j] in roots or (parents[j] >= 0 and inside[parents[j]])
    return np.flatnonzero(inside)


def hand_bones(body: BodyModel) -> np.ndarray:
    """Indices of the wrist joints and every joint below them (the fingers); empty when the
    body names no wrists."""
    return _subtree_bones(body, ("left_wrist", "right_wrist"))


def leg_bones(body: BodyModel) -> np.ndarray:
    """Indices of the hip joints and every joint below them; empty when the body names no hips."""
    return _subtree_bones(body, ("left_hip", "right_hip"))


def drawn_faces(body: BodyModel, cfg: RenderConfig) -> np.ndarray:
    """The reference body's faces that are drawn: with `render.upper_body`, not the legs' (every
    vertex's dominant skinning bone a hip or below), as the robot's legs are hidden: signing
    is upper-body, and they were a quarter of the drawn triangles."""
    faces = np.asarray(body.faces)
    if not cfg.upper_body:
        return faces
    legs = np.isin(np.asarray(body.skin_weights).argmax(axis=1), leg_bones(body))
    return faces[~legs[faces].all(axis=1)]


def reference_cells(body: BodyModel, cfg: RenderConfig) -> np.ndarray:
    """Decimation cell (m) per reference vertex: `reference_cell_m` on the hands (by dominant
    skinning bone), `reference_body_cell_m` elsewhere."""
    bones = np.asarray(body.skin_weights).argmax(axis=1)
    coarse = cfg.reference_cell_m if cfg.reference_body_cell_m is None else cfg.reference_body_cell_m
    return np.where(np.isin(bones, hand_bones(body)), cfg.reference_cell_m, coarse)


def open_renderer(robot, body: BodyModel, fit, cfg: RenderConfig) -> SceneRenderer:
    """A renderer for this robot with the fitted body as reference mesh; `renderer.skin`
    gives the drawn mesh's vertices of a motion's frames (a `ReferenceSkin`). When that
    skinning is exact linear blend skinning, the body is also bound as a MuJoCo skin, and
    `draw_reference` draws it from bone poses."""
    with torch.no_grad():
        betas = torch.as_tensor(fit.betas, dtype=torch.float64)
        rest = body.rest_vertices(betas)
        reach = reach_poses()
        reach_verts = body.vertices(reach, betas)
        points = fit.apply(reach_verts).cpu().numpy().reshape(-1, 3)
    bones = np.asarray(body.skin_weights).argmax(axis=1)
    renderer = SceneRenderer(robot, cfg, drawn_faces(body, cfg), rest.cpu().numpy(),
                             torso_body=robot.spec.torso_body, reference_points=points,
                             reference_groups=bones, reference_cells=reference_cells(body, cfg))
    try:
        skin = renderer.skin = ReferenceSkin(body, fit, renderer.reference_keep, reach, reach_verts)
        if skin.exact and is_similarity(fit.scale, fit.rotation):
            # linear blend skinning, mapped rigidly and scaled: MuJoCo can skin the drawn mesh
            with torch.no_grad():
                bind = body.rest_joints(betas).cpu().numpy()
            renderer.bind_reference_skin(rest.cpu().numpy()[renderer.reference_keep],
                                         np.asarray(body.skin_weights)[renderer.reference_keep],
                                         bind, fit.scale, fit.rotation, fit.offset)
    except Exception:
        renderer.close()
        raise
    return renderer


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


def draw_reference(renderer: SceneRenderer, motion: Motion, frames: np.ndarray,
                   view: str = "front", full: bool = False, out: np.ndarray | None = None,
                   crop: Crop | None = None) -> np.ndarray:
    """Images of the reference body at `frames` of `motion`: from bone poses when the renderer
    has a bound skin (`open_renderer` binds one for linear blend skinning), else from the
    skinned vertices (`renderer.skin`); `full`, `out`, `crop` as in `SceneRenderer.robot_frames`."""
    if len(frames) == 0:  # nothing to draw (e.g. a chunk without keyframes)
        if out is not None:
            return out
        w, h = renderer.size if full else (renderer.cfg.width, renderer.cfg.height)
        if crop is not None:
            w, h = crop[2] - crop[0], crop[3] - crop[1]
        return np.zeros((0, h, w, 3), dtype=np.uint8)
    if renderer.posed:
        return renderer.reference_pose_frames(renderer.skin.transforms(motion, frames), view,
                                              full=full, out=out, crop=crop)
    return renderer.reference_frames(renderer.skin(motion, frames), view, full=full, out=out,
                                     crop=crop)


def render_comparison(renderer: SceneRenderer, cfg: RenderConfig, keyframes: np.ndarray,
                      fps: float, q: np.ndarray, reference: dict[str, np.ndarray] | None = None,
                      reference_verts: np.ndarray | None = None,
                      drawn: "PreviewFrames | None" = None,
                      motion: Motion | None = None) -> Comparison:
    """Render robot keyframes (and the reference ones unless given: drawn from `motion` with
    `draw_reference`, else from `reference_verts`). Views and keyframes that `drawn` (the
    preview's frames) already holds are not drawn again."""
    keyframes = np.asarray(keyframes)
    comp = Comparison(keyframes, fps)
    for view in cfg.views:
        reused = drawn.at(view, keyframes) if drawn is not None else None
        if reused is not None:
            comp.reference[view], comp.robot[view] = (downsample(x, cfg.supersample) for x in reused)
            continue
        comp.robot[view] = renderer.robot_frames(q[keyframes], view)
        if reference is not None:
            comp.reference[view] = reference[view]
        elif motion is not None:
            comp.reference[view] = draw_reference(renderer, motion, keyframes, view)
        else:
            comp.reference[view] = renderer.reference_frames(reference_verts, view)
    return comp


@dataclass
class PreviewFrames:
    """Images as drawn (supersampled) of some preview frames, reference and robot, one view."""

    view: str
    frames: np.ndarray
    reference: np.ndarray
    robot: np.ndarray

    def at(self, view: str, keyframes: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(reference, robot) images of `keyframes` when all were drawn for the preview."""
        if view != self.view or len(self.frames) == 0:
            return None
        where = np.minimum(np.searchsorted(self.frames, keyframes), len(self.frames) - 1)
        if not np.array_equal(self.frames[where], keyframes):
            return None
        return self.reference[where], self.robot[where]


def preview_frames(cfg: RenderConfig, num_frames: int, fps: float) -> tuple[np.ndarray, float]:
    """(source frame indices, playback fps) of the preview: `render.preview_fps` frames a
    second of motion (every frame at the source rate when it is null or higher), evenly
    subsampled beyond `render.preview_max_frames`; playback is real time either way."""
    duration = num_frames / fps
    rate = fps if cfg.preview_fps is None else min(cfg.preview_fps, fps)
    count = int(np.clip(round(duration * rate), min(2, num_frames),
                        min(cfg.preview_max_frames, num_frames)))
    frames = np.unique(np.linspace(0, num_frames - 1, count).round().astype(np.int64))
    return frames, len(frames) / duration


def preview_crop(renderer: SceneRenderer, motion: Motion, q: np.ndarray, frames: np.ndarray,
                 view: str, margin: int = _CROP_MARGIN) -> Crop | None:
    """The part of the drawn image (`renderer.size`) that the bounding spheres of the robot's
    geoms and of the reference body's bones reach at `frames`, plus `margin` pixels,
    even-sized (x264's 4:2:0); one box for both bodies, so the side-by-side halves keep one
    scale and line up. None when it would not be smaller than the whole image, or when the
    reference is drawn from vertices (no bound skin)."""
    if renderer.skin is not None and not renderer.posed:
        return None
    centres, radii = renderer.robot_spheres(q[frames])
    boxes = [renderer.pixel_bounds(centres.reshape(-1, 3), np.tile(radii, len(frames)), view,
                                   margin)]
    if renderer.skin is not None:
        bones, radii = renderer.reference_spheres(renderer.skin.transforms(motion, frames))
        boxes.append(renderer.pixel_bounds(bones.reshape(-1, 3), np.tile(radii, len(frames)),
                                           view, margin))
    if any(b is None for b in boxes):
        return None
    (w, h), box = renderer.size, np.array(boxes)
    x0, y0 = int(box[:, 0].min()), int(box[:, 1].min())
    x1, y1 = int(box[:, 2].max()), int(box[:, 3].max())
    x0, x1 = _even(x0, x1, w)
    y0, y1 = _even(y0, y1, h)
    if (x1 - x0) * (y1 - y0) >= w * h or x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _even(lo: int, hi: int, size: int) -> tuple[int, int]:
    """Widen [lo, hi) by a pixel, where it fits, to an even length (the drawn size is even)."""
    if (hi - lo) % 2:
        if hi < size:
            hi += 1
        else:
            lo -= 1
    return lo, hi


def stream_preview(renderer: SceneRenderer, cfg: RenderConfig, motion: Motion, q: np.ndarray,
                   path: Path, keep: np.ndarray | None = None) -> tuple[Path | None, PreviewFrames]:
    """Draw the preview (first view; reference | robot side by side at the drawn size,
    `render.supersample` × width × height per body: 1280×480 by default, or the part of it
    the bodies reach with `render.preview_crop`) chunk by chunk into the encoder. The frames in
    `keep` (the sheet's keyframes) are drawn whole in the same pass, also where the preview
    skips them; the preview's frames among them are cut from those images. Returns the file
    written (None when `preview_format` is none: nothing drawn) and the drawn images of `keep`
    (the sheet reuses them)."""
    view = cfg.views[0]
    shown, rate = preview_frames(cfg, len(q), motion.fps)
    keep = np.unique(np.asarray(keep if keep is not None else [], dtype=np.int64))
    kept: dict[str, list[np.ndarray]] = {"reference": [], "robot": []}
    if cfg.preview_format == "none":
        return None, PreviewFrames(view, keep[:0], np.zeros((0,)), np.zeros((0,)))
    keep = keep[(keep >= 0) & (keep < len(q))]
    w, h = renderer.size
    crop = preview_crop(renderer, motion, q, shown, view) if cfg.preview_crop else None
    x0, y0, x1, y1 = crop if crop is not None else (0, 0, w, h)
    cw, ch = x1 - x0, y1 - y0
    writer = PreviewWriter(path, rate, cfg.preview_format)
    frames = np.union1d(shown, keep)
    for start in range(0, len(frames), _CHUNK):
        chunk = frames[start:start + _CHUNK]
        keys, show = chunk[np.isin(chunk, keep)], chunk[np.isin(chunk, shown)]
        # the keyframes whole, both bodies straight into their halves of side-by-side frames
        whole = np.empty((len(keys), h, 2 * w, 3), dtype=np.uint8)
        draw_reference(renderer, motion, keys, view, full=True, out=whole[:, :, :w])
        renderer.robot_frames(q[keys], view, full=True, out=whole[:, :, w:])
        kept["reference"].append(whole[:, :, :w])
        kept["robot"].append(whole[:, :, w:])
        # the preview's other frames: only the crop drawn
        rest = show[~np.isin(show, keys)]
        part = np.empty((len(rest), ch, 2 * cw, 3), dtype=np.uint8)
        draw_reference(renderer, motion, rest, view, full=True, out=part[:, :, :cw], crop=crop)
        renderer.robot_frames(q[rest], view, full=True, out=part[:, :, cw:], crop=crop)
        video = np.empty((len(show), ch, 2 * cw, 3), dtype=np.uint8)
        video[np.isin(show, rest)] = part
        cut = np.isin(keys, show)
        video[~np.isin(show, rest), :, :cw] = whole[cut, y0:y1, x0:x1]
        video[~np.isin(show, rest), :, cw:] = whole[cut, y0:y1, w + x0:w + x1]
        writer.add(video)
    out = writer.close()
    return out, PreviewFrames(view, keep, np.concatenate(kept["reference"]),
                              np.concatenate(kept["robot"]))


def render_preview(renderer: SceneRenderer, cfg: RenderConfig, motion: Motion, body: BodyModel,
                   fit, q: np.ndarray, path: Path) -> Path | None:
    """Side-by-side reference | robot animation at the source frame rate (`stream_preview`)."""
    return stream_preview(renderer, cfg, motion, np.asarray(q), path)[0]
