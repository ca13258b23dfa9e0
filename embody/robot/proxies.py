"""Proxies of the robot's collision geoms, for a differentiable self-collision cost.

Two kinds, both fitted to the collision geoms (mesh vertices, primitive extremes) at the T-pose:

* spheres: `chain` (along a limb's principal axis) or `cluster` (k-means cover), rigidly attached
  to the proxy's first body; or `points`: `spheres` surface points (radius 0) per geom on the
  geom's own body, sampled from its convex hull, which follow a limb's exact surface.
* `hull`: each geom's convex hull (MuJoCo collides meshes as their hulls) as a polytope of at
  most `planes` planes, each pushed out to touch the full hull, so the polytope contains it.
  The signed distance of a point is the largest plane distance: exact inside and on faces, an
  underestimate near edges (the safe side).

Sphere/sphere pairs keep hands apart; sphere/hull pairs keep arm surfaces off the torso shell
whose 8 mm gap to the hanging upper arm no sphere cover can resolve. All of it is cheap to
evaluate for every frame; MuJoCo's exact contacts remain the verdict (`embody.robot.contacts`).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial import ConvexHull

from embody.robot.model import Robot


def _geom_points(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> np.ndarray:
    """World points that bound geom g (at the current kinematics)."""
    pos, mat = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    size = model.geom_size[g]
    kind = model.geom_type[g]
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        local = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        local = np.vstack([np.zeros(3), size[0] * np.vstack([np.eye(3), -np.eye(3)])])
    # `==`, not `in (...)`: from mujoco 3.12 a numpy int is never found in a tuple of enum members
    elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE or kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        r, h = size[0], size[1]
        ring = np.array([[r * np.cos(a), r * np.sin(a)] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
        local = np.vstack([np.column_stack([ring, np.full(8, z)]) for z in (-h, h)])
        if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            local = np.vstack([local, [[0, 0, -h - r], [0, 0, h + r]]])
    elif kind == mujoco.mjtGeom.mjGEOM_BOX:
        local = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
    else:
        local = np.zeros((1, 3))
    return pos + local @ mat.T


def _sphere_chain(points: np.ndarray, k: int, cover: float) -> tuple[np.ndarray, np.ndarray]:
    """k spheres along the principal axis that cover (most of) the points."""
    centre = points.mean(0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    axis = vt[0]
    t = (points - centre) @ axis
    edges = np.linspace(t.min(), t.max(), k + 1)
    perp = np.linalg.norm((points - centre) - t[:, None] * axis, axis=1)
    overall = float(np.percentile(perp, 100 * cover))
    centres, radii = [], []
    for i in range(k):
        sel = (t >= edges[i]) & (t <= edges[i + 1])
        centres.append(centre + axis * 0.5 * (edges[i] + edges[i + 1]))
        radii.append(float(np.percentile(perp[sel], 100 * cover)) if sel.sum() >= 4 else overall)
    return np.array(centres), np.array(radii)


def _sphere_cluster(points: np.ndarray, k: int, cover: float, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """k spheres from deterministic k-means (farthest-point init), each covering `cover` of its points."""
    centres = [points.mean(0)]
    for _ in range(1, k):
        d = np.min([np.linalg.norm(points - c, axis=1) for c in centres], axis=0)
        centres.append(points[int(np.argmax(d))])
    c = np.array(centres)
    for _ in range(iterations):
        label = np.argmin(np.linalg.norm(points[:, None] - c[None], axis=-1), axis=1)
        c = np.array([points[label == i].mean(0) if np.any(label == i) else c[i] for i in range(k)])
    label = np.argmin(np.linalg.norm(points[:, None] - c[None], axis=-1), axis=1)
    radii = np.array([np.percentile(np.linalg.norm(points[label == i] - c[i], axis=1), 100 * cover)
                      if np.any(label == i) else 0.0 for i in range(k)])
    return c, radii


def _farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """k well-spread points (deterministic farthest-point sampling from the first)."""
    chosen = [0]
    d = np.linalg.norm(points - points[0], axis=1)
    for _ in range(1, min(k, len(points))):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen]


def _hull_planes(points: np.ndarray, planes: int) -> np.ndarray:
    """≤ `planes` planes (n, d), n·x + d ≤ 0 inside, whose polytope contains `points`' hull."""
    verts = points[ConvexHull(points).vertices]
    k = max(4, planes // 2 + 2)  # a hull of k points has at most 2k − 4 faces
    eq = ConvexHull(_farthest_points(verts, k)).equations
    eq = np.unique(np.round(eq, 9), axis=0)[:planes]
    eq[:, 3] = -(verts @ eq[:, :3].T).max(0)  # push each plane out to touch the full hull
    return eq


@dataclass
class Proxies:
    """Spheres and hulls per proxy, attached to bodies; sphere/sphere and sphere/hull pairs."""

    names: list[str]
    bodies: list[str]
    sphere_body: np.ndarray
    sphere_part: np.ndarray
    centres: np.ndarray
    radii: np.ndarray
    pairs: np.ndarray  # (P, 2) sphere index pairs
    hull_body: np.ndarray  # (H,) index into bodies
    hull_planes: np.ndarray  # (H, F, 4) in the body frame, padded by repeating a plane
    hull_centre: np.ndarray  # (H, 3) bounding-sphere centre in the body frame
    hull_radius: np.ndarray  # (H,)
    hull_box: np.ndarray  # (H, 2, 3) bounding box (lower, upper corner) in the body frame
    hull_pairs: np.ndarray  # (Q, 2) (sphere, hull) pairs

    @classmethod
    def fit(cls, robot: Robot) -> "Proxies":
        model = robot.model
        data = mujoco.MjData(model)
        data.qpos[:] = robot.qpos(robot.tpose)
        mujoco.mj_kinematics(model, data)
        groups = set(robot.spec.collision.geom_groups)
        body_names = [model.body(b).name for b in range(model.nbody)]
        names: list[str] = list(robot.spec.proxies)
        bodies: list[str] = []
        s_body, s_part, centres, radii = [], [], [], []
        h_body, h_part, h_planes, h_centre, h_radius, h_box = [], [], [], [], [], []

        def local(points: np.ndarray, b: int) -> tuple[np.ndarray, int]:
            if body_names[b] not in bodies:
                bodies.append(body_names[b])
            r, pos = data.xmat[b].reshape(3, 3), data.xpos[b]
            return (points - pos) @ r, bodies.index(body_names[b])

        for p, (name, ps) in enumerate(robot.spec.proxies.items()):
            matched = [b for b, n in enumerate(body_names)
                       if any(fnmatch.fnmatchcase(n, pat) for pat in ps.bodies)]
            geoms = [g for b in matched for g in range(model.ngeom)
                     if model.geom_bodyid[g] == b and model.geom_group[g] in groups]
            if ps.geoms:
                geoms = [geoms[i] for i in ps.geoms if i < len(geoms)]
            if not geoms:
                raise ValueError(f"proxy {name!r}: no collision geoms")
            if ps.layout in ("hull", "points"):
                for g in geoms:
                    pts, bi = local(_geom_points(model, data, g), int(model.geom_bodyid[g]))
                    if ps.layout == "hull":
                        h_planes.append(_hull_planes(pts, ps.planes))
                        mid = (pts.min(0) + pts.max(0)) / 2
                        h_centre.append(mid)
                        h_radius.append(float(np.linalg.norm(pts - mid, axis=1).max()))
                        h_box.append([pts.min(0), pts.max(0)])
                        h_body.append(bi)
                        h_part.append(p)
                    else:
                        c = _farthest_points(pts[ConvexHull(pts).vertices], ps.spheres)
                        centres.append(c)
                        radii.append(np.zeros(len(c)))
                        s_body += [bi] * len(c)
                        s_part += [p] * len(c)
                continue
            points = np.vstack([_geom_points(model, data, g) for g in geoms])
            pts, bi = local(points, matched[0])  # spheres ride on the first matching body
            c, rad = (_sphere_chain if ps.layout == "chain" else _sphere_cluster)(pts, ps.spheres, ps.cover)
            s_body += [bi] * len(c)
            s_part += [p] * len(c)
            centres.append(c)
            radii.append(rad)
        s_part_arr, h_part_arr = np.array(s_part), np.array(h_part)
        pairs, hull_pairs = [], []
        for a, b in robot.spec.proxy_pairs:
            ia, ib = np.flatnonzero(s_part_arr == names.index(a)), np.flatnonzero(s_part_arr == names.index(b))
            ha, hb = np.flatnonzero(h_part_arr == names.index(a)), np.flatnonzero(h_part_arr == names.index(b))
            if (len(ha) and len(hb)) or (len(ha) and len(ia)) or (len(hb) and len(ib)):
                raise ValueError(f"proxy pair {a}/{b}: hulls pair only with sphere proxies")
            pairs += [(i, j) for i in ia for j in ib]
            hull_pairs += [(i, h) for i in ia for h in hb] + [(i, h) for i in ib for h in ha]
        n_planes = max((len(e) for e in h_planes), default=1)
        planes = np.array([np.vstack([e, np.repeat(e[:1], n_planes - len(e), 0)]) for e in h_planes])
        return cls(names=names, bodies=bodies, sphere_body=np.array(s_body), sphere_part=s_part_arr,
                   centres=np.vstack(centres), radii=np.concatenate(radii),
                   pairs=np.array(pairs, dtype=np.int64).reshape(-1, 2),
                   hull_body=np.array(h_body, dtype=np.int64), hull_planes=planes.reshape(-1, n_planes, 4),
                   hull_centre=np.array(h_centre).reshape(-1, 3), hull_radius=np.array(h_radius),
                   hull_box=np.array(h_box).reshape(-1, 2, 3),
                   hull_pairs=np.array(hull_pairs, dtype=np.int64).reshape(-1, 2))


_CACHE: dict[int, Proxies] = {}


def robot_proxies(robot: Robot) -> Proxies:
    """Proxies of a loaded robot, fitted once per Robot object."""
    key = id(robot)
    if key not in _CACHE:
        _CACHE[key] = Proxies.fit(robot)
    return _CACHE[key]
