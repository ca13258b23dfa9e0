"""Legible renders: the light robot stands out from the background at 320×240, and the framing
holds the head and both hands of robot and human, for robots of different heights (G1, H1), at
the T-pose and with the arms raised, in the front and the side view."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.body import load_body_model
from embody.config import load_config
from embody.config.render import RenderConfig
from embody.render import SceneRenderer
from embody.render.compare import open_renderer
from embody.render.framing import project
from embody.retarget import shape_fit
from embody.robot import load_robot

ROBOTS = ("unitree_g1_dex3", "unitree_h1")
LUMA = np.array([0.2126, 0.7152, 0.0722])


def _background(cfg: RenderConfig) -> np.ndarray:
    return np.round(np.asarray(cfg.background_rgb) * 255)


def _robot_pixels(img: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    return np.abs(img.astype(float) - _background(cfg)).max(axis=-1) > 0


def _inner(mask: np.ndarray) -> np.ndarray:
    """Robot pixels whose 4 neighbours are robot too: the surface, not its antialiased outline
    (outline pixels are blends with the background by design)."""
    inner = mask.copy()
    inner[1:] &= mask[:-1]
    inner[:-1] &= mask[1:]
    inner[:, 1:] &= mask[:, :-1]
    inner[:, :-1] &= mask[:, 1:]
    return inner


def _joint(robot, side: str, part: str) -> int:
    return next(i for i, n in enumerate(robot.joint_names) if n.startswith(f"{side}_shoulder_{part}"))


def _poses(robot) -> dict[str, np.ndarray]:
    """T-pose; arms raised sideways (roll at its limit); arms raised forward-up (pitch at its limit)."""
    side_up, front_up = robot.tpose.copy(), robot.tpose.copy()
    for side in ("left", "right"):
        roll, pitch = _joint(robot, side, "roll"), _joint(robot, side, "pitch")
        side_up[roll] = robot.upper[roll] if side == "left" else robot.lower[roll]
        front_up[roll], front_up[pitch] = 0.0, robot.lower[pitch]
    return {"tpose": robot.tpose, "arms_side_up": side_up, "arms_front_up": front_up}


@pytest.fixture(scope="module")
def robots():
    cfg = load_config()
    return {name: load_robot(cfg.robot.model_copy(update={"name": name})) for name in ROBOTS}


def _image_points(renderer, robot, q: np.ndarray, view: str, links: list[str]) -> np.ndarray:
    """Pixel positions of robot links at q, projected with the renderer's own camera."""
    pos, _ = robot.link_poses(q[None], links)
    world_from_torso = np.linalg.inv(robot.torso_from_world)
    world = pos[0] @ world_from_torso[:3, :3].T + world_from_torso[:3, 3]
    cam = renderer.camera(view)
    return project(renderer._model, np.array(cam.lookat), cam.distance, cam.azimuth,
                   cam.elevation, world, renderer.cfg.width, renderer.cfg.height)


@pytest.mark.parametrize("name", ROBOTS)
def test_light_robot_contrasts_with_the_background(robots, name):
    robot = robots[name]
    cfg = RenderConfig()  # the default: 320×240, light robot, neutral light background
    assert (cfg.width, cfg.height) == (320, 240) and cfg.views == ["front", "side"]
    bg_luma = _background(cfg) @ LUMA
    assert bg_luma > 140  # a light background, not the old black
    renderer = SceneRenderer(robot, cfg, torso_body=robot.spec.torso_body)
    try:
        for view in cfg.views:
            img = renderer.robot_frames(robot.rest[None], view)[0]
            mask = _robot_pixels(img, cfg)
            assert mask.mean() > 0.02, (view, mask.mean())
            mask = _inner(mask)
            contrast = np.abs(img[mask].astype(float) @ LUMA - bg_luma)
            assert np.median(contrast) >= 40, (view, np.median(contrast))
            assert (contrast > 20).mean() >= 0.75, (view, (contrast > 20).mean())
            # the hands themselves read: robot pixels around each wrist stand out too
            for xy in _image_points(renderer, robot, robot.rest, view, ["left_wrist", "right_wrist"]):
                x, y = np.round(xy).astype(int)
                win = (slice(max(y - 8, 0), y + 9), slice(max(x - 8, 0), x + 9))
                hand = mask[win]
                assert hand.sum() >= 10, (view, xy)
                assert np.median(np.abs(img[win][hand].astype(float) @ LUMA - bg_luma)) >= 25
    finally:
        renderer.close()


@pytest.mark.parametrize("name", ROBOTS)
def test_framing_holds_head_and_hands_of_robot_and_human(robots, name):
    robot = robots[name]
    cfg0 = load_config()
    body = load_body_model(cfg0.body)
    fit = shape_fit(robot, body, cfg0.ik)
    cfg = RenderConfig(width=160, height=120, preview_format="none")  # framing depends on aspect only
    renderer = open_renderer(robot, body, fit, cfg)
    try:
        for pose_name, q in _poses(robot).items():
            for view in cfg.views:
                img = renderer.robot_frames(q[None], view)[0]
                mask = _robot_pixels(img, cfg)
                border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
                assert not border.any(), f"{name} {pose_name} {view}: robot cut at the frame edge"
                xy = _image_points(renderer, robot, q, view, ["head", "left_wrist", "right_wrist"])
                assert np.all((xy > 0) & (xy < [cfg.width, cfg.height])), (pose_name, view, xy)
        # the human reference (shape-fitted, in the torso frame) at the T-pose and arms raised
        pose = torch.zeros((2, 55, 3), dtype=torch.float64)
        pose[1, 16, 2], pose[1, 17, 2] = np.pi / 2 * 0.95, -np.pi / 2 * 0.95  # shoulders: arms up
        with torch.no_grad():
            verts = fit.apply(body.vertices(pose, torch.as_tensor(fit.betas))).numpy()
        for view in cfg.views:
            for img in renderer.reference_frames(verts, view):
                human = _robot_pixels(img, cfg)
                assert human.mean() > 0.02
                # head and hands inside: top, left and right edges clear (legs leave at the bottom)
                assert not np.concatenate([human[0], human[:, 0], human[:, -1]]).any(), (name, view)
    finally:
        renderer.close()
