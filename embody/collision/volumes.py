"""Part volumes: convex pieces per rigid body part, tight enough to stand in for the body.

Every joint that owns vertices by dominant skinning weight (fingers segment by segment, so the
pieces follow the hand's articulation) gets the convex hull of its rest vertices in its joint
frame, reduced to `MAX_PIECE_VERTICES` corners (bounded planes keep the energy cheap). A hull
that overfills its part (volume outside the closed body mesh) by more than `max_overfill` is
replaced by a deterministic CoACD decomposition (seed 0) of hull ∩ body. `cover` then moves the
planes out just enough that every vertex of the part lies inside its own pieces. Results are
cached in memory and on disk (`$EMBODY_CACHE` or `~/.cache/embody`), keyed by a hash of the
shaped rest mesh, skinning and construction settings."""

from __future__ import annotations

import hashlib
import io
import os
import threading
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from embody.body.base import BodyModel, ConvexPiece
from embody.cache import cache_dir
from embody.body.parts import dominant_parts

#: Bump when the construction changes, so stale disk caches are ignored.
VERSION = 6
#: Vertices kept per convex piece: bounds the planes the energy evaluates per point.
MAX_PIECE_VERTICES = 32
#: Parts with fewer vertices (or flat ones) get no volume.
MIN_PART_VERTICES = 8
#: CoACD concavity thresholds tried in turn until the part is tight enough.
COACD_THRESHOLDS = (0.1, 0.05)

_memory: dict[str, "PartVolumes"] = {}
#: Per body, each (betas bytes, max_overfill) seen: its `_mesh_key`. Why: the key hashes the
#: shaped rest mesh and the skin weights (~6 ms), and the collide step asks for the same
#: shape's volumes several times per sequence (every `collision_model` call).
_keys: weakref.WeakKeyDictionary[BodyModel, dict[tuple[bytes, float], str]] = \
    weakref.WeakKeyDictionary()
_lock = threading.Lock()


def piece_joint_name(name: str) -> str:
    """Joints whose vertices ride on another joint: zero-length hand joints and the face."""
    side, _, rest = name.partition("_")
    if rest == "hand":
        return f"{side}_wrist"
    if name == "jaw" or rest == "eye":
        return "head"
    return name


@dataclass(frozen=True)
class PartVolumes:
    """Convex pieces (joint-local) of each rigid part, plus how well they fit the body."""

    part_names: tuple[str, ...]
    part_joints: np.ndarray
    #: Rest-mesh vertex → part (V,); -1 for the vertices of parts too small for a volume.
    vertex_parts: np.ndarray
    pieces: tuple[ConvexPiece, ...]
    hull_volume: np.ndarray
    overfill: np.ndarray
    key: str

    def report(self) -> pd.DataFrame:
        counts = np.bincount([p.part for p in self.pieces], minlength=len(self.part_names))
        return pd.DataFrame({"part": self.part_names, "pieces": counts,
                             "hull_volume_cm3": self.hull_volume * 1e6,
                             "overfill_pct": self.overfill * 100.0})


def rest_frames(body: BodyModel, betas: np.ndarray) -> np.ndarray:
    """World transforms (J,4,4) of the zero pose, float64."""
    b = torch.as_tensor(np.asarray(betas, dtype=np.float64))
    return body.joint_transforms(torch.zeros(1, 55, 3, dtype=torch.float64), b)[0].numpy()


def to_local(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    return (points - frame[:3, 3]) @ frame[:3, :3]


def _fps(points: np.ndarray, k: int) -> np.ndarray:
    """Deterministic farthest-point subset, starting from the point farthest from the centroid."""
    if len(points) <= k:
        return points
    chosen = [int(np.argmax(((points - points.mean(0)) ** 2).sum(1)))]
    dist = ((points - points[chosen[0]]) ** 2).sum(1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, ((points - points[chosen[-1]]) ** 2).sum(1))
    return points[np.sort(chosen)]


def hull(points: np.ndarray,
         max_vertices: int = MAX_PIECE_VERTICES) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, planes) of the convex hull, reduced to at most `max_vertices` vertices."""
    points = np.asarray(points, dtype=np.float64)
    try:
        h = ConvexHull(points)
    except QhullError:
        h = ConvexHull(points, qhull_options="QJ")
    verts = _fps(points[h.vertices], max_vertices)
    try:
        h = ConvexHull(verts)
    except QhullError:
        h = ConvexHull(verts, qhull_options="QJ")
    return verts[h.vertices], np.ascontiguousarray(h.equations)


def cover(pieces: list[tuple[np.ndarray, np.ndarray]],
          points: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Push each piece's planes out just enough to contain the points nearest to it.

    Simplified hulls and CoACD pieces leave some of the part's own vertices outside; keeping
    the plane normals and moving the offsets keeps each piece convex and small, and guarantees
    that every vertex lies inside its own part's volume.
    """
    f = np.stack([np.max(points @ pl[:, :3].T + pl[:, 3], axis=1) for _, pl in pieces])
    owner = np.argmin(f, axis=0)
    out = []
    for k, (verts, planes) in enumerate(pieces):
        mine = points[owner == k]
        if len(mine) == 0 or f[k, owner == k].max() <= 0:
            out.append((verts, planes))
            continue
        planes = planes.copy()
        planes[:, 3] = np.minimum(planes[:, 3], -(mine @ planes[:, :3].T).max(0))
        centre = np.concatenate([verts, mine]).mean(0)
        corners = HalfspaceIntersection(planes, centre).intersections
        out.append((corners[ConvexHull(corners).vertices], planes))
    return out


def _manifold(vertices: np.ndarray, faces: np.ndarray):
    import manifold3d as m3

    return m3.Manifold(m3.Mesh(vert_properties=np.asarray(vertices, np.float32),
                               tri_verts=np.asarray(faces, np.uint32)))


def closed_body(vertices: np.ndarray, faces: np.ndarray):
    """The body as one solid (union of its closed components), or None if it is not closed."""
    import manifold3d as m3
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    solid = None
    for comp in mesh.split(only_watertight=False):
        m = _manifold(comp.vertices, comp.faces)
        if m.status() != m3.Error.NoError or m.is_empty():
            return None
        solid = m if solid is None else solid + m
    return solid


def _overfill(pieces_world: list[np.ndarray], body_solid) -> tuple[float, float]:
    """(hull volume m³, fraction of the pieces' union outside the body)."""
    import manifold3d as m3

    union = m3.Manifold.batch_boolean([m3.Manifold.hull_points(v) for v in pieces_world],
                                      m3.OpType.Add)
    vol = union.volume()
    if body_solid is None or vol <= 0:
        return vol, float("nan")
    return vol, float(1.0 - (union ^ body_solid).volume() / vol)


def _coacd(solid, threshold: float, max_vertices: int) -> list[np.ndarray]:
    import coacd

    coacd.set_log_level("error")
    mesh = solid.to_mesh()
    parts = coacd.run_coacd(
        coacd.Mesh(np.asarray(mesh.vert_properties[:, :3], np.float64),
                   np.asarray(mesh.tri_verts, np.int64)),
        threshold=threshold, seed=0, max_ch_vertex=max_vertices, preprocess_mode="off",
        mcts_iterations=40, mcts_nodes=10, resolution=1000)
    return [np.asarray(v, np.float64) for v, _ in parts if len(v) >= 4]


def _mesh_key(body: BodyModel, rest: np.ndarray, frames: np.ndarray, max_overfill: float) -> str:
    h = hashlib.sha256()
    for a in (np.round(rest, 6), np.round(frames, 6), body.faces, body.skin_weights.round(4)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(f"{body.name}|{VERSION}|{max_overfill:.6g}|{MAX_PIECE_VERTICES}".encode())
    return h.hexdigest()[:24]


def part_volumes(body: BodyModel, betas: np.ndarray | None = None, *,
                 max_overfill: float = 0.10) -> PartVolumes:
    """Convex pieces of every rigid part for this body and shape (memory + disk cached)."""
    betas = np.zeros(10) if betas is None else np.asarray(betas, dtype=np.float64)
    shape = (betas.tobytes(), float(max_overfill))
    with _lock:
        known = _keys.get(body, {}).get(shape)
        if known is not None and known in _memory:
            return _memory[known]
    rest = body.rest_vertices(torch.as_tensor(betas)).double().numpy()
    frames = rest_frames(body, betas)
    key = _mesh_key(body, rest, frames, max_overfill)
    with _lock:
        _keys.setdefault(body, {})[shape] = key
        if key in _memory:
            return _memory[key]
    path = cache_dir() / "collision" / f"volumes-{key}.npz"
    vols = _load(path, key) if path.exists() else None
    if vols is None:
        vols = _build(body, rest, frames, max_overfill, key)
        _save(vols, path)
    with _lock:
        _memory[key] = vols
    return vols


def _build(body: BodyModel, rest: np.ndarray, frames: np.ndarray, max_overfill: float,
           key: str) -> PartVolumes:
    parts = dominant_parts(body.skin_weights, list(body.joint_names), merge=piece_joint_name)
    solid = closed_body(rest, body.faces)
    pieces: list[ConvexPiece] = []
    hull_vol, overfill = [], []
    kept: list[int] = []
    for i, j in enumerate(parts.joints):
        frame = frames[j]
        world = rest[parts.vertex_parts == i]
        if len(world) < MIN_PART_VERTICES or np.linalg.matrix_rank(world - world.mean(0)) < 3:
            continue  # too small to enclose a volume (only in toy meshes)
        kept.append(i)
        i = len(kept) - 1
        local = to_local(world, frame)
        to_world = lambda c: [pv @ frame[:3, :3].T + frame[:3, 3] for pv, _ in c]  # noqa: E731
        single = hull(local)
        candidates = [cover([single], local)]
        vol, over = _overfill(to_world([single]), solid)
        scores = [_overfill(to_world(candidates[0]), solid)[1]]
        if solid is not None and scores[0] > max_overfill:
            import manifold3d as m3

            inside = m3.Manifold.hull_points(to_world([single])[0]) ^ solid
            for thr in COACD_THRESHOLDS:
                split = [hull(to_local(p, frame)) for p in _coacd(inside, thr, MAX_PIECE_VERTICES)]
                if not split:
                    continue
                candidates.append(cover(split, local))
                scores.append(_overfill(to_world(candidates[-1]), solid)[1])
                if scores[-1] <= max_overfill:
                    break
        best = int(np.nanargmin(scores)) if np.isfinite(scores).any() else 0
        pieces += [ConvexPiece(part=i, joint=int(j), vertices=pv, planes=pp)
                   for pv, pp in candidates[best]]
        hull_vol.append(vol)
        overfill.append(scores[best])
    remap = np.full(len(parts.joints), -1, dtype=np.int64)
    remap[kept] = np.arange(len(kept))
    joints = parts.joints[kept]
    return PartVolumes(tuple(body.joint_names[j] for j in joints), joints,
                       remap[parts.vertex_parts], tuple(pieces), np.array(hull_vol),
                       np.array(overfill), key)


def _save(vols: PartVolumes, path: Path) -> None:
    """Atomic write (temp file + rename) so parallel workers never read half a cache."""
    arrays = {"part_joints": vols.part_joints, "vertex_parts": vols.vertex_parts,
              "hull_volume": vols.hull_volume, "overfill": vols.overfill,
              "part_names": np.array(vols.part_names),
              "piece_part": np.array([p.part for p in vols.pieces]),
              "piece_nverts": np.array([len(p.vertices) for p in vols.pieces]),
              "piece_nplanes": np.array([len(p.planes) for p in vols.pieces]),
              "vertices": np.concatenate([p.vertices for p in vols.pieces]),
              "planes": np.concatenate([p.planes for p in vols.pieces])}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_bytes(buf.getvalue())
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache only costs recomputation


def _load(path: Path, key: str) -> PartVolumes | None:
    try:
        with np.load(path) as d:
            a = {k: d[k] for k in d.files}
    except (OSError, ValueError, KeyError):
        return None
    vsplit = np.cumsum(a["piece_nverts"])[:-1]
    psplit = np.cumsum(a["piece_nplanes"])[:-1]
    joints = a["part_joints"]
    pieces = tuple(ConvexPiece(part=int(p), joint=int(joints[p]), vertices=v, planes=pl)
                   for p, v, pl in zip(a["piece_part"], np.split(a["vertices"], vsplit),
                                       np.split(a["planes"], psplit)))
    return PartVolumes(tuple(str(n) for n in a["part_names"]), joints, a["vertex_parts"], pieces,
                       a["hull_volume"], a["overfill"], key)


def overfill_report(body: BodyModel, betas: np.ndarray | None = None, *,
                    max_overfill: float = 0.10) -> pd.DataFrame:
    """Per part: pieces, single-hull volume (cm³) and overfill (% of the pieces' union outside
    the closed body mesh; NaN when the mesh is not closed)."""
    return part_volumes(body, betas, max_overfill=max_overfill).report()
