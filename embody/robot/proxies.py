"""Sphere-chain proxies of the robot's collision geoms, for a differentiable self-collision cost.

Each proxy (hand, forearm, torso, ...) gets `spheres` spheres fitted to its collision-geom
points (mesh vertices, primitive extremes) taken at the T-pose, rigidly attached to its first
body: laid along the principal axis for limbs (`chain`) or a k-means cover for bulky parts
(`cluster`). Spheres are cheap to evaluate for every frame of a sequence and give
smooth gradients; MuJoCo's exact contacts remain the verdict (`embody.retarget.verify`).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

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
    elif kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
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


@dataclass
class Proxies:
    """Spheres (local centres, radii) per proxy, attached to bodies; pairs to keep apart."""

    names: list[str]
    bodies: list[str]
    sphere_body: np.ndarray
    sphere_part: np.ndarray
    centres: np.ndarray
    radii: np.ndarray
    pairs: np.ndarray  # (P, 2) sphere index pairs from the configured proxy pairs

    @classmethod
    def fit(cls, robot: Robot) -> "Proxies":
        model = robot.model
        data = mujoco.MjData(model)
        data.qpos[:] = robot.qpos(robot.tpose)
        mujoco.mj_kinematics(model, data)
        groups = set(robot.spec.collision.geom_groups)
        body_names = [model.body(b).name for b in range(model.nbody)]
        names, bodies, s_body, s_part, centres, radii = [], [], [], [], [], []
        for p, (name, ps) in enumerate(robot.spec.proxies.items()):
            matched = [b for b, n in enumerate(body_names)
                       if any(fnmatch.fnmatchcase(n, pat) for pat in ps.bodies)]
            geoms = [g for b in matched for g in range(model.ngeom)
                     if model.geom_bodyid[g] == b and model.geom_group[g] in groups]
            if ps.geoms:
                geoms = [geoms[i] for i in ps.geoms if i < len(geoms)]
            if not geoms:
                raise ValueError(f"proxy {name!r}: no collision geoms")
            points = np.vstack([_geom_points(model, data, g) for g in geoms])
            anchor = matched[0]  # spheres ride on the first matching body
            r, pos = data.xmat[anchor].reshape(3, 3), data.xpos[anchor]
            local = (points - pos) @ r
            c, rad = (_sphere_chain if ps.layout == "chain" else _sphere_cluster)(local, ps.spheres, ps.cover)
            if body_names[anchor] not in bodies:
                bodies.append(body_names[anchor])
            names.append(name)
            s_body += [bodies.index(body_names[anchor])] * len(c)
            s_part += [p] * len(c)
            centres.append(c)
            radii.append(rad)
        s_part_arr = np.array(s_part)
        pairs = []
        for a, b in robot.spec.proxy_pairs:
            ia = np.flatnonzero(s_part_arr == names.index(a))
            ib = np.flatnonzero(s_part_arr == names.index(b))
            pairs += [(i, j) for i in ia for j in ib]
        return cls(names=names, bodies=bodies, sphere_body=np.array(s_body), sphere_part=s_part_arr,
                   centres=np.vstack(centres), radii=np.concatenate(radii),
                   pairs=np.array(pairs, dtype=np.int64))

    def world_centres(self, robot: Robot, q: torch.Tensor) -> torch.Tensor:
        """Sphere centres (B,N,3) in the torso frame."""
        return self.centres_from(robot.body_transforms(q, self.bodies))

    def centres_from(self, transforms: torch.Tensor) -> torch.Tensor:
        """Sphere centres (B,N,3) from torso-frame transforms (B,len(bodies),4,4) of `bodies`."""
        t = transforms[:, torch.as_tensor(self.sphere_body, device=transforms.device)]
        c = torch.as_tensor(self.centres, dtype=t.dtype, device=t.device)
        return (t[..., :3, :3] @ c[..., None])[..., 0] + t[..., :3, 3]

    def clearances(self, centres: torch.Tensor) -> torch.Tensor:
        """Signed sphere-pair clearances (B,P): distance minus both radii (negative = overlap)."""
        i = torch.as_tensor(self.pairs[:, 0], device=centres.device)
        j = torch.as_tensor(self.pairs[:, 1], device=centres.device)
        r = torch.as_tensor(self.radii, dtype=centres.dtype, device=centres.device)
        d = torch.linalg.norm(centres[:, i] - centres[:, j] + 1e-12, dim=-1)
        return d - r[i] - r[j]

    def penalty(self, centres: torch.Tensor, margin: float) -> torch.Tensor:
        """Per-frame penalty (B,): Σ relu(margin − clearance)², zero when every pair is clear."""
        return torch.relu(margin - self.clearances(centres)).pow(2).sum(-1)


_CACHE: dict[int, Proxies] = {}


def robot_proxies(robot: Robot) -> Proxies:
    """Proxies of a loaded robot, fitted once per Robot object."""
    key = id(robot)
    if key not in _CACHE:
        _CACHE[key] = Proxies.fit(robot)
    return _CACHE[key]
