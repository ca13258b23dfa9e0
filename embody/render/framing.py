"""Camera framing that fits the robot and the reference body, for any robot size.

A fixed look-at point and distance suit one robot: a taller robot (H1) loses its head and raised
hands off the frame. Here the frame is derived from the robot itself, at the T-pose: the visible
upper-body geoms (head included), plus each arm's reach sphere about its shoulder (radius = the
farthest arm geom from the shoulder), which contains every pose of that arm, raised hands
included. Points of the reference body (already mapped into the torso frame by the shape fit) can
be added, so both bodies fit. The same look-at point and distance serve every view and both
bodies, so human and robot images line up pixel for pixel and keep one scale across views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import mujoco

#: Fraction of the half-extent added on every side.
MARGIN = 0.06
#: Reach below the shoulder kept in frame, as a fraction of the arm length: hands at the belly
#: and in the lap are in frame; arms hanging straight down by the thighs (not signing) may be cut.
REACH_DOWN = 0.6


@dataclass(frozen=True)
class Framing:
    """A free camera's look-at point (torso frame, metres) and distance, shared by all views."""

    lookat: np.ndarray
    distance: float


def _subtree(model: mujoco.MjModel, root: int) -> np.ndarray:
    inside = np.zeros(model.nbody, dtype=bool)
    for b in range(model.nbody):  # parents precede children in MuJoCo's body order
        inside[b] = b == root or (b > 0 and inside[model.body_parentid[b]])
    return inside


def _directions() -> np.ndarray:
    """26 unit directions (cube corners, edges, faces) to sample a sphere's extent."""
    grid = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                     if (x, y, z) != (0, 0, 0)], dtype=np.float64)
    return grid / np.linalg.norm(grid, axis=1, keepdims=True)


def robot_points(model: mujoco.MjModel, qpos: np.ndarray, torso_from_world: np.ndarray,
                 visible: np.ndarray, shoulders: list[str]) -> np.ndarray:
    """Points (N,3), torso frame, that the frame must hold: the visible geoms at `qpos` (each
    as its bounding sphere) and every arm's reach sphere about its shoulder, down to
    `REACH_DOWN` arm lengths below it. `visible` masks drawn geoms; `shoulders` are body
    names whose subtrees are the arms."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    rot, pos = torso_from_world[:3, :3], torso_from_world[:3, 3]
    centres = data.geom_xpos @ rot.T + pos
    radius = model.geom_rbound.copy()
    # mesh bounding spheres are loose; the half-diagonal of the geom's own box is tighter
    tight = np.linalg.norm(model.geom_aabb[:, 3:], axis=1)
    radius = np.where(tight > 0, np.minimum(radius, tight), radius)
    keep = visible & (radius > 0)
    dirs = _directions()
    points = [(centres[keep, None, :] + radius[keep, None, None] * dirs).reshape(-1, 3)]
    for name in shoulders:
        body = model.body(name).id
        arm = _subtree(model, body)[model.geom_bodyid] & keep
        if not arm.any():
            continue
        shoulder = data.xpos[body] @ rot.T + pos
        reach = float((np.linalg.norm(centres[arm] - shoulder, axis=1) + radius[arm]).max())
        sphere = shoulder + reach * dirs
        sphere[:, 2] = np.maximum(sphere[:, 2], shoulder[2] - REACH_DOWN * reach)
        points.append(sphere)
    return np.concatenate(points)


def fit_camera(points: np.ndarray, fovy_deg: float, aspect: float,
               views: tuple[str, ...] = ("front", "side"), margin: float = MARGIN) -> Framing:
    """Look-at point (the points' box centre) and the smallest distance at which every point
    is inside the frame in every view, plus `margin`. Front looks along −x, side along −y."""
    pts = np.asarray(points, dtype=np.float64)
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    rel = (pts - centre) * (1 + margin)
    t = np.tan(np.radians(fovy_deg) / 2)
    distance = 0.0
    for view in views:
        # (horizontal, toward the camera) axes; vertical is z in both views
        w, d = (rel[:, 1], rel[:, 0]) if view == "front" else (rel[:, 0], rel[:, 1])
        need = d + np.maximum(np.abs(rel[:, 2]) / t, np.abs(w) / (aspect * t))
        distance = max(distance, float(need.max()))
    return Framing(centre, distance)


def project(model: mujoco.MjModel, framing_lookat_world: np.ndarray, distance: float,
            azimuth: float, elevation: float, points_world: np.ndarray, width: int,
            height: int) -> np.ndarray:
    """Pixel coordinates (N,2) (x right, y down) of world points seen by a MuJoCo free camera.

    The same pinhole model MuJoCo renders with (vertical field of view `model.vis.global_.fovy`);
    tests use it to check that body points land inside the image.
    """
    az, el = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    eye = np.asarray(framing_lookat_world, dtype=np.float64) - distance * forward
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = np.asarray(points_world, dtype=np.float64) - eye
    x, y, z = rel @ right, rel @ up, rel @ forward
    f = (height / 2) / np.tan(np.radians(model.vis.global_.fovy) / 2)
    return np.stack([width / 2 + f * x / z, height / 2 - f * y / z], axis=1)


def pixel_bounds(model: mujoco.MjModel, lookat_world: np.ndarray, distance: float,
                 azimuth: float, elevation: float, centres_world: np.ndarray,
                 radii: np.ndarray | float, width: int, height: int,
                 margin: int = 0) -> tuple[int, int, int, int] | None:
    """The smallest pixel box (x0, y0, x1, y1; end-exclusive, top row 0) inside the image that
    holds every sphere (centres (N,3) world, radii (N,) or one radius) as seen by the free
    camera of `project`, plus `margin` pixels; None when a sphere reaches behind the camera.
    A point within r of a centre at depth z, (x, y) off the axis, projects within
    f·r/(z − r)·(1 + |x|/z) pixels of the centre's projection horizontally (likewise
    vertically), f being the focal length in pixels."""
    az, el = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    eye = np.asarray(lookat_world, dtype=np.float64) - distance * forward
    centres = np.asarray(centres_world, dtype=np.float64).reshape(-1, 3)
    radii = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(centres),))
    depth = (centres - eye) @ forward
    if len(centres) == 0 or np.any(depth - radii <= 1e-3):
        return None
    f = (height / 2) / np.tan(np.radians(model.vis.global_.fovy) / 2)
    uv = project(model, lookat_world, distance, azimuth, elevation, centres, width, height)
    spread = f * radii / (depth - radii)
    rx = spread * (1 + np.abs(uv[:, 0] - width / 2) / f) + margin
    ry = spread * (1 + np.abs(uv[:, 1] - height / 2) / f) + margin
    x0 = int(np.clip(np.floor((uv[:, 0] - rx).min()), 0, width))
    x1 = int(np.clip(np.ceil((uv[:, 0] + rx).max()), 0, width))
    y0 = int(np.clip(np.floor((uv[:, 1] - ry).min()), 0, height))
    y1 = int(np.clip(np.ceil((uv[:, 1] + ry).max()), 0, height))
    return x0, y0, x1, y1
