"""Offscreen MuJoCo rendering of the robot and of the reference body from the same cameras.

Two models share one GL context: a private copy of the robot model, and a model of the reference
body. The body is a MuJoCo skin on one mocap body per bone when its skinning is linear blend
skinning (`bind_reference_skin`): a frame is then only bone poses, MuJoCo skins and re-uploads the
vertex buffer itself, ~3× cheaper on software GL than rewriting a mesh and rebuilding its display
list (`mjr_uploadMesh`), which stays the path for vertices given directly.
Both are placed in the robot torso frame's world pose at the T-pose and seen through identical
free cameras, so reference and robot line up pixel for pixel; the framing fits both bodies
(`embody.render.framing`). Shadows, reflections and skybox are off and (by default) the legs are
hidden: signing is upper-body and this halves the render time. The robot is drawn in one light
material, and every pixel left at the clear colour (pure black, which no lit surface here
reaches) gets the neutral background colour.

Software GL (Mesa llvmpipe) pays per triangle and for a multisample resolve, hardly per pixel:
so both bodies' meshes are decimated for drawing, multisampling is off, and images are drawn at
`render.supersample` × the configured size and box-filtered down (the preview takes them as
drawn). Reading back colour only (no depth buffer) saves most of the read-back time.
"""

from __future__ import annotations

import copy
import hashlib
import threading
from typing import Protocol

import numpy as np
import scipy.sparse

from embody.config.render import RenderConfig
from embody.render.framing import Framing, fit_camera, pixel_bounds, robot_points
from embody.render.gl import create_context

import mujoco  # noqa: E402  (after embody.render.gl has set MUJOCO_GL)

_OFF_FLAGS = (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
              mujoco.mjtRndFlag.mjRND_SKYBOX, mujoco.mjtRndFlag.mjRND_FOG,
              mujoco.mjtRndFlag.mjRND_HAZE)
_HIDDEN_GROUP = 5
_MESH = mujoco.mjtGeom.mjGEOM_MESH
#: Robot links whose subtrees (the hands) keep the fine `mesh_cell_m`; `robot_body_cell_m`
#: elsewhere.
_FINE_LINKS = ("left_wrist", "right_wrist")
#: Shadows are off, but every `MjrContext` allocates its shadow map: at MuJoCo's default 4096²
#: that costs ~30 ms a context on software GL, at this size nothing.
_SHADOW_SIZE = 64
#: Robot models prepared for drawing (decimated, recoloured), per process: preparing G1's takes
#: about half a second and every sequence's renderer needs the same one. Read-only once built.
_PREPARED: dict[tuple, tuple[mujoco.MjModel, mujoco.MjModel]] = {}
_PREPARED_LOCK = threading.Lock()
#: `cluster_faces` results by content (`_clustered`), per process.
_CLUSTERED: dict[str, tuple[np.ndarray, np.ndarray]] = {}


#: Part of a drawn image: x0, y0, x1, y1 in pixels (top row 0), end-exclusive.
Crop = tuple[int, int, int, int]


class RenderableRobot(Protocol):
    """What rendering needs of `embody.robot.Robot`."""

    model: mujoco.MjModel
    torso_from_world: np.ndarray

    def qpos(self, q: np.ndarray) -> np.ndarray: ...


def _subtree_mask(model: mujoco.MjModel, root: int) -> np.ndarray:
    """Per geom: does its body descend from (or equal) body `root`?"""
    inside = np.zeros(model.nbody, dtype=bool)
    for b in range(model.nbody):  # parents precede children in MuJoCo's body order
        inside[b] = b == root or (b > 0 and inside[model.body_parentid[b]])
    return inside[model.geom_bodyid]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V,3)."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    idx = faces.ravel()
    weights = np.repeat(fn, 3, axis=0)
    vn = np.stack([np.bincount(idx, weights[:, c], minlength=len(vertices)) for c in range(3)], 1)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def downsample(images: np.ndarray, factor: int) -> np.ndarray:
    """Box-filter images (...,H·f,W·f,3) uint8 down by `factor` (rounded, deterministic)."""
    if factor == 1:
        return images
    # integer sums are exact in any order: the f² strided sub-images added up (several times
    # faster than numpy's reduction over the two interleaved block axes), in 16 bits where
    # they fit (f ≤ 15: half the memory traffic of 32)
    h, w = images.shape[-3] // factor * factor, images.shape[-2] // factor * factor
    n = factor * factor
    total = images[..., 0:h:factor, 0:w:factor, :].astype(np.uint16 if n * 256 <= 1 << 16 else np.uint32)
    total += n // 2
    for i in range(factor):
        for j in range(factor):
            if i or j:
                total += images[..., i:h:factor, j:w:factor, :]
    total //= n
    return total.astype(np.uint8)


def cluster_faces(vertices: np.ndarray, faces: np.ndarray, cell: float | np.ndarray,
                  groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering of a deformable mesh for drawing: (kept vertex indices (K,), faces (F',3)
    indexing the kept vertices). Vertices merge only within one grid cell of `cell` metres (at
    the rest shape) and one connected piece of the mesh and one `groups` label (e.g. the dominant
    skinning bone), so separate pieces, such as fingers, never get bridged when they move apart.
    `cell` may be given per vertex (V,) (constant within a group: fine hands, a coarse torso);
    vertices with a cell of 0 are kept as they are."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    cells = np.broadcast_to(np.asarray(cell, dtype=np.float64), (n,))
    if not (cells > 0).any():
        return np.arange(n), faces
    adjacency = scipy.sparse.coo_matrix(
        (np.ones(faces.size), (faces.ravel(), np.roll(faces, 1, axis=1).ravel())), shape=(n, n))
    _, piece = scipy.sparse.csgraph.connected_components(adjacency, directed=False)
    labels = [piece] + ([np.asarray(groups, dtype=np.int64)] if groups is not None else [])
    alone = np.where(cells > 0, -1, np.arange(n))  # a cell of 0: the vertex is its own cluster
    grid = np.floor(vertices / np.where(cells > 0, cells, 1.0)[:, None]).astype(np.int64)
    size = np.round(cells * 1e6).astype(np.int64)  # grids of different cells never share keys
    key = np.column_stack(labels + [alone, size, grid])
    _, first, label = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rep = first[label.ravel()][faces]
    rep = rep[(rep[:, 0] != rep[:, 1]) & (rep[:, 1] != rep[:, 2]) & (rep[:, 0] != rep[:, 2])]
    _, uniq = np.unique(np.sort(rep, axis=1), axis=0, return_index=True)
    rep = rep[np.sort(uniq)]
    keep = np.unique(rep)
    return keep, np.searchsorted(keep, rep)


def is_similarity(scale: float, rotation: np.ndarray) -> bool:
    """Is p ↦ scale · rotation @ p a positive scale times a proper rotation (what a bound skin
    can draw: `SceneRenderer.bind_reference_skin`)?"""
    r = np.asarray(rotation, dtype=np.float64)
    return bool(scale > 0 and r.shape == (3, 3) and np.allclose(r @ r.T, np.eye(3), atol=1e-6)
                and np.linalg.det(r) > 0)


def _clustered(vertices: np.ndarray, faces: np.ndarray, cell: float | np.ndarray,
               groups: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """`cluster_faces`, remembered per process by the inputs' content: every sequence of a run
    draws the same fitted body (~35 ms a renderer otherwise); each caller gets its own copies."""
    arrays = [np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
              np.asarray(cell, dtype=np.float64)]
    if groups is not None:
        arrays.append(np.asarray(groups, dtype=np.int64))
    digest = hashlib.blake2b(digest_size=16)
    for a in arrays:
        digest.update(repr(a.shape).encode())
        digest.update(np.ascontiguousarray(a).tobytes())
    key = digest.hexdigest()
    with _PREPARED_LOCK:
        hit = _CLUSTERED.get(key)
    if hit is None:
        hit = cluster_faces(vertices, faces, cell, groups)
        with _PREPARED_LOCK:
            if len(_CLUSTERED) >= 8:
                _CLUSTERED.clear()
            _CLUSTERED[key] = hit
    return hit[0].copy(), hit[1].copy()


def cluster_mesh(model: mujoco.MjModel, mesh: int, cell: float) -> None:
    """Decimate one mesh in place by vertex clustering on a `cell`-sized grid.

    Menagerie's G1 upper body has ~470k triangles, which software GL draws at ~4 frames/s; a
    grid finer than a pixel at the camera distance keeps the look at a fraction of the cost.
    Faces are rewritten at the front of the mesh's face block and `mesh_facenum` shrinks; each
    surviving vertex gets a fresh area-weighted normal (normals are per vertex in these meshes).
    """
    vadr, vnum = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
    fadr, fnum = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
    nadr, nnum = model.mesh_normaladr[mesh], model.mesh_normalnum[mesh]
    if nnum != vnum or fnum < 64:
        return  # normals not per vertex (or tiny mesh): leave it
    verts = model.mesh_vert[vadr:vadr + vnum].astype(np.float64)
    faces = model.mesh_face[fadr:fadr + fnum]
    _, first, label = np.unique(np.floor(verts / cell).astype(np.int64), axis=0,
                                return_index=True, return_inverse=True)
    new = first[label.ravel()][faces]
    new = new[(new[:, 0] != new[:, 1]) & (new[:, 1] != new[:, 2]) & (new[:, 0] != new[:, 2])]
    if len(new) == 0:
        return
    _, keep = np.unique(np.sort(new, axis=1), axis=0, return_index=True)
    new = new[np.sort(keep)]
    model.mesh_face[fadr:fadr + len(new)] = new
    model.mesh_facenormal[fadr:fadr + len(new)] = new
    model.mesh_facenum[mesh] = len(new)
    model.mesh_normal[nadr:nadr + nnum] = vertex_normals(verts, new)


def prepared_robot_model(robot: "RenderableRobot", cfg: RenderConfig, torso_body: str = "torso_link",
                         model: mujoco.MjModel | None = None) -> mujoco.MjModel:
    """The robot model as drawn (a private copy: decimated, recoloured, legs hidden, offscreen
    buffer sized), built once per process for the same model and render config. No GL: a
    worker's parent can build it before forking, so each worker's first renderer starts
    without it (~0.3 CPU-s on G1)."""
    model = robot.model if model is None else model
    size = (cfg.width * cfg.supersample, cfg.height * cfg.supersample)
    key = (id(model), torso_body, size, cfg.upper_body, cfg.mesh_cell_m, cfg.robot_body_cell_m,
           tuple(cfg.robot_rgba))
    with _PREPARED_LOCK:
        source, prepared = _PREPARED.get(key, (None, None))
        if source is model:  # the entry holds its source, so its id cannot be reused
            return prepared
    prepared = _prepare(robot, cfg, model, torso_body, size)
    with _PREPARED_LOCK:
        if len(_PREPARED) >= 8:
            _PREPARED.clear()
        _PREPARED[key] = (model, prepared)
    return prepared


def _prepare(robot: "RenderableRobot", cfg: RenderConfig, model: mujoco.MjModel,
             torso_body: str, size: tuple[int, int]) -> mujoco.MjModel:
    model = copy.copy(model)  # private: we change offscreen size and geom groups
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, size[0])
    model.vis.global_.offheight = max(model.vis.global_.offheight, size[1])
    model.vis.quality.offsamples = 0  # supersampled instead (see the module docstring)
    model.vis.quality.shadowsize = _SHADOW_SIZE
    if cfg.upper_body:
        upper = _subtree_mask(model, model.body(torso_body).id)
        model.geom_group[~upper] = _HIDDEN_GROUP
    cells = np.full(model.nmesh, cfg.mesh_cell_m)
    if cfg.robot_body_cell_m is not None:  # coarser outside the hands
        links = getattr(getattr(robot, "spec", None), "links", {}) or {}
        hands = np.zeros(model.ngeom, dtype=bool)
        for name in _FINE_LINKS:
            if name in links:
                hands |= _subtree_mask(model, model.body(links[name].body).id)
        if hands.any():
            mesh = model.geom_type == _MESH
            body_meshes = np.setdiff1d(model.geom_dataid[~hands & mesh],
                                       model.geom_dataid[hands & mesh])
            cells[body_meshes[body_meshes >= 0]] = cfg.robot_body_cell_m
    for mesh in np.flatnonzero(cells > 0):
        cluster_mesh(model, int(mesh), float(cells[mesh]))
    model.geom_matid[:] = -1  # one light material instead of the robot's dark ones
    model.geom_rgba[:] = cfg.robot_rgba
    model.vis.headlight.ambient[:] = 0.45
    model.vis.headlight.diffuse[:] = 0.55
    model.vis.headlight.specular[:] = 0.2
    return model


class SceneRenderer:
    """Renders robot configurations and reference meshes; close it (or use `with`) when done."""

    def __init__(self, robot: RenderableRobot, cfg: RenderConfig,
                 faces: np.ndarray | None = None, rest_vertices: np.ndarray | None = None,
                 torso_body: str = "torso_link",
                 reference_points: np.ndarray | None = None,
                 reference_groups: np.ndarray | None = None,
                 reference_cells: np.ndarray | None = None) -> None:
        """`reference_points` (N,3), torso frame: reference body points the framing must hold.
        `reference_groups` (V,): labels (the dominant skinning bone) whose vertices may merge
        when the reference mesh is decimated; `reference_cells` (V,): the grid cell per vertex
        (default `render.reference_cell_m` everywhere)."""
        self.cfg = cfg
        self.robot = robot
        self.world_from_torso = np.linalg.inv(np.asarray(robot.torso_from_world, dtype=np.float64))
        #: Drawn image size (width, height): the configured size × `supersample`.
        self.size = (cfg.width * cfg.supersample, cfg.height * cfg.supersample)
        #: Indices of the reference mesh's vertices that are drawn (all unless decimated).
        self.reference_keep: np.ndarray | None = None
        #: Vertices of the drawn reference mesh per motion frame (`compare.open_renderer` sets it).
        self.skin = None
        self._ctx = create_context(*self.size, cfg.gl)
        self._contexts: list[mujoco.MjrContext] = []
        try:
            self._model = self._robot_model(robot.model, torso_body)
            self.framing = self._framing(reference_points)
            self._data = mujoco.MjData(self._model)
            self._robot_ctx = self._context(self._model)
            self._scene = mujoco.MjvScene(self._model, maxgeom=self._model.ngeom + 100)
            self._mesh: _MeshModel | None = None
            self._skin: _SkinModel | None = None
            if faces is not None and rest_vertices is not None:
                cells = cfg.reference_cell_m if reference_cells is None else reference_cells
                keep, kept_faces = _clustered(rest_vertices, faces, cells, reference_groups)
                self.reference_keep = keep
                self._reference_count = len(rest_vertices)
                self._kept_faces = kept_faces
                self._kept_rest = np.asarray(rest_vertices)[keep]
        except Exception:
            self.close()
            raise
        self._rect = mujoco.MjrRect(0, 0, *self.size)
        self._background = np.round(np.asarray(cfg.background_rgb) * 255).astype(np.uint8)
        self._option = mujoco.MjvOption()  # groups 0-2 visible: robot visuals, no collision meshes
        #: Background painted in GL (`_fill_background_gl`): None until the first image checks it.
        self._gl_fill: bool | None = None
        self._pixels = np.empty((self.size[1], self.size[0], 3), dtype=np.uint8)  # read-back
        self._crop_pixels: dict[tuple[int, int], np.ndarray] = {}  # read-back per crop size

    # --- setup ----------------------------------------------------------------------------

    def _robot_model(self, model: mujoco.MjModel, torso_body: str) -> mujoco.MjModel:
        return prepared_robot_model(self.robot, self.cfg, torso_body, model)

    def _framing(self, reference_points: np.ndarray | None) -> Framing:
        """Configured look-at/distance, or a framing that fits robot (and reference) in every view."""
        if self.cfg.lookat is not None and self.cfg.camera_distance is not None:
            return Framing(np.asarray(self.cfg.lookat, dtype=np.float64), self.cfg.camera_distance)
        model = self._model
        tpose = np.asarray(getattr(self.robot, "tpose", np.zeros(0)), dtype=np.float64)
        qpos = self.robot.qpos(tpose) if tpose.size else model.qpos0.copy()
        links = getattr(getattr(self.robot, "spec", None), "links", {}) or {}
        shoulders = [links[n].body for n in ("left_shoulder", "right_shoulder") if n in links]
        visible = model.geom_group < 3  # what MjvOption's default groups draw
        points = robot_points(model, qpos, np.asarray(self.robot.torso_from_world), visible,
                              shoulders)
        if reference_points is not None and len(reference_points):
            ref = np.asarray(reference_points, dtype=np.float64).reshape(-1, 3)
            # the upper body: legs are below the signing space (and hidden on the robot)
            points = np.concatenate([points, ref[ref[:, 2] >= points[:, 2].min()]])
        auto = fit_camera(points, float(model.vis.global_.fovy), self.cfg.width / self.cfg.height,
                          tuple(self.cfg.views))
        lookat = auto.lookat if self.cfg.lookat is None else np.asarray(self.cfg.lookat, float)
        distance = auto.distance if self.cfg.camera_distance is None else self.cfg.camera_distance
        return Framing(lookat, distance)

    def _context(self, model: mujoco.MjModel) -> mujoco.MjrContext:
        ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, ctx)
        self._contexts.append(ctx)
        return ctx

    def camera(self, view: str) -> mujoco.MjvCamera:
        """The fixed free camera of a view ("front" or "side", seen from the robot's left)."""
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        rot, pos = self.world_from_torso[:3, :3], self.world_from_torso[:3, 3]
        cam.lookat[:] = pos + rot @ self.framing.lookat
        forward = -rot[:, 0] if view == "front" else -rot[:, 1]
        cam.azimuth = float(np.degrees(np.arctan2(forward[1], forward[0])))
        cam.elevation = self.cfg.camera_elevation
        cam.distance = self.framing.distance
        return cam

    # --- rendering ------------------------------------------------------------------------

    def _draw(self, model, data, scene, ctx, cam, into: np.ndarray | None = None,
              crop: Crop | None = None) -> np.ndarray:
        """One image (H,W,3), top row first; written into `into` when given (no extra copy).
        With `crop` (x0, y0, x1, y1; drawn pixels, top row 0) only that part of the image is
        drawn, through the matching off-centre frustum: the same pixels as cutting it out of
        the whole image, at the cost of the smaller one."""
        mujoco.mjv_updateScene(model, data, self._option, None, cam,
                               mujoco.mjtCatBit.mjCAT_ALL, scene)
        for flag in _OFF_FLAGS:
            scene.flags[flag] = 0
        rect, out = self._rect, self._pixels
        if crop is not None:
            rect, out = self._crop_view(scene, crop)
        # each MjrContext owns a framebuffer; bind this one's (the last created is bound)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, ctx)
        mujoco.mjr_render(rect, scene, ctx)
        filled = self._gl_fill is not False and _fill_background_gl(self._background)
        mujoco.mjr_readPixels(out, None, rect, ctx)
        flat = out.reshape(-1, 3)
        if self._gl_fill is None:  # first image: check that the GL fill left no clear colour
            self._gl_fill = bool(filled) and not _black(flat).any()
        if not self._gl_fill:
            flat[_black(flat)] = self._background  # still the clear colour
        if into is None:
            return out[::-1].copy()
        into[...] = out[::-1]
        return into

    def _crop_view(self, scene: mujoco.MjvScene, crop: Crop) -> tuple[mujoco.MjrRect, np.ndarray]:
        """Narrow the scene's cameras to `crop`; the viewport and read-back buffer for it."""
        x0, y0, x1, y1 = crop
        w, h = self.size
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise ValueError(f"crop {crop} is not inside the drawn image {self.size}")
        for cam in scene.camera:
            top = cam.frustum_top
            half = top * w / h  # MuJoCo's half-width from the viewport's aspect
            left, right = -half + 2 * half * x0 / w, -half + 2 * half * x1 / w
            cam.frustum_center, cam.frustum_width = (left + right) / 2, (right - left) / 2
            cam.frustum_top, cam.frustum_bottom = top - 2 * top * y0 / h, top - 2 * top * y1 / h
        size = (x1 - x0, y1 - y0)
        if size not in self._crop_pixels:
            self._crop_pixels[size] = np.empty((size[1], size[0], 3), np.uint8)
        return mujoco.MjrRect(0, 0, *size), self._crop_pixels[size]

    def _finish(self, frames: list[np.ndarray], full: bool, out: np.ndarray | None) -> np.ndarray:
        if out is not None:
            return out
        images = np.stack(frames) if frames else np.zeros((0, self.size[1], self.size[0], 3), np.uint8)
        return images if full else downsample(images, self.cfg.supersample)

    def _target(self, out: np.ndarray | None, n: int, full: bool, crop: Crop | None = None) -> None:
        w, h = self.size if crop is None else (crop[2] - crop[0], crop[3] - crop[1])
        if crop is not None and not full:
            raise ValueError("a crop is drawn as drawn: full=True")
        if out is not None and (not full or out.shape != (n, h, w, 3)):
            raise ValueError(f"out must be ({n}, {h}, {w}, 3) with full=True")

    def pixel_bounds(self, centres_world: np.ndarray, radii: np.ndarray | float, view: str,
                     margin: int = 0) -> Crop | None:
        """Pixel box of the drawn image (`self.size`) holding these world-frame spheres in
        `view` (`framing.pixel_bounds`)."""
        cam = self.camera(view)
        return pixel_bounds(self._model, np.array(cam.lookat), cam.distance, cam.azimuth,
                            cam.elevation, centres_world, radii, *self.size, margin=margin)

    def reference_spheres(self, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Spheres (centres (N,B,3) world, radii (B,)) holding the bound skin posed by joint
        transforms (N,J,4,4), one per bone (`_SkinModel.bone_spheres`)."""
        if self._skin is None:
            raise ValueError("no reference skin bound (bind_reference_skin)")
        return self._skin.bone_spheres(np.asarray(transforms, dtype=np.float64))

    def robot_spheres(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bounding spheres of the drawn robot geoms at configurations q (N,n): centres (N,G,3)
        and radii (G,), world frame (each geom's bounding box about its centre)."""
        visible = np.flatnonzero(self._model.geom_group < 3)  # what `self._option` draws
        box = self._model.geom_aabb[visible]
        radii = np.linalg.norm(box[:, 3:], axis=1)
        centres = np.empty((len(np.atleast_2d(q)), len(visible), 3))
        data = mujoco.MjData(self._model)
        for i, qi in enumerate(np.atleast_2d(q)):
            data.qpos[:] = self.robot.qpos(np.asarray(qi, dtype=np.float64))
            mujoco.mj_kinematics(self._model, data)
            rot = data.geom_xmat[visible].reshape(-1, 3, 3)
            centres[i] = data.geom_xpos[visible] + np.einsum("gab,gb->ga", rot, box[:, :3])
        return centres, radii

    def robot_frames(self, q: np.ndarray, view: str = "front", full: bool = False,
                     out: np.ndarray | None = None, crop: Crop | None = None) -> np.ndarray:
        """Images (N,H,W,3) of joint configurations q (N,n) in the robot's joint order; at the
        configured size, or as drawn (`self.size`, supersampled) with `full`, then written into
        `out` when given (e.g. one half of the preview's side-by-side frames); only the `crop`
        of the drawn image when given (`_draw`)."""
        q = np.atleast_2d(q)
        self._target(out, len(q), full, crop)
        self._ctx.make_current()
        cam = self.camera(view)
        frames = []
        for i, qi in enumerate(q):
            self._data.qpos[:] = self.robot.qpos(np.asarray(qi, dtype=np.float64))
            mujoco.mj_kinematics(self._model, self._data)
            frames.append(self._draw(self._model, self._data, self._scene, self._robot_ctx, cam,
                                     None if out is None else out[i], crop))
        return self._finish(frames, full, out)

    def reference_frames(self, vertices: np.ndarray, view: str = "front",
                         full: bool = False, out: np.ndarray | None = None,
                         crop: Crop | None = None) -> np.ndarray:
        """Images (N,H,W,3) of reference meshes given as (N,V,3) vertices in the torso frame:
        every vertex of the mesh, or only the drawn ones (`reference_keep`); `full`, `out` and
        `crop` as in `robot_frames`."""
        if self.reference_keep is None:
            raise ValueError("SceneRenderer was built without a reference mesh (faces, rest_vertices)")
        vertices = np.asarray(vertices)
        if vertices.shape[1] != len(self.reference_keep):
            if vertices.shape[1] != self._reference_count:
                raise ValueError(f"reference vertices: expected {self._reference_count} or "
                                 f"{len(self.reference_keep)} per frame, got {vertices.shape[1]}")
            vertices = vertices[:, self.reference_keep]
        self._target(out, len(vertices), full, crop)
        self._ctx.make_current()
        if self._mesh is None:  # built on first use: the posed path (a bound skin) needs none
            self._mesh = _MeshModel(self._kept_faces, self._kept_rest, self.cfg,
                                    self._model.vis.global_.fovy, self.size)
            self._mesh_ctx = self._context(self._mesh.model)
            self._mesh_scene = mujoco.MjvScene(self._mesh.model, maxgeom=16)
        cam = self.camera(view)
        rot, pos = self.world_from_torso[:3, :3], self.world_from_torso[:3, 3]
        frames = []
        for i, verts in enumerate(np.asarray(vertices, dtype=np.float64)):
            self._mesh.set_vertices(verts @ rot.T + pos, self._mesh_ctx)
            frames.append(self._draw(self._mesh.model, self._mesh.data, self._mesh_scene,
                                     self._mesh_ctx, cam, None if out is None else out[i], crop))
        return self._finish(frames, full, out)

    def bind_reference_skin(self, rest_vertices: np.ndarray, weights: np.ndarray,
                            bind: np.ndarray, scale: float, rotation: np.ndarray,
                            offset: np.ndarray) -> None:
        """Draw the reference body as a MuJoCo skin from bone poses (`reference_pose_frames`).
        `rest_vertices` (K,3) and `weights` (K,J) of the drawn vertices (`reference_keep`) and
        the bind joints (J,3), all in the body frame, which maps into the torso frame as
        p ↦ scale · rotation @ p + offset (a similarity: `rotation` proper)."""
        if self.reference_keep is None:
            raise ValueError("SceneRenderer was built without a reference mesh (faces, rest_vertices)")
        rotation = np.asarray(rotation, dtype=np.float64)
        if not is_similarity(scale, rotation):
            raise ValueError("the body-to-torso map must be a positive scale times a rotation")
        rot, pos = self.world_from_torso[:3, :3], self.world_from_torso[:3, 3]
        self._ctx.make_current()
        self._skin = _SkinModel(self._kept_faces, rest_vertices, weights, bind, scale,
                                rot @ rotation, rot @ np.asarray(offset, np.float64) + pos,
                                self.cfg, self._model.vis.global_.fovy, self.size)
        self._skin_ctx = self._context(self._skin.model)
        self._skin_scene = mujoco.MjvScene(self._skin.model, maxgeom=16)

    @property
    def posed(self) -> bool:
        """Whether the reference body can be drawn from bone poses (`bind_reference_skin`)."""
        return self._skin is not None

    def reference_pose_frames(self, transforms: np.ndarray, view: str = "front",
                              full: bool = False, out: np.ndarray | None = None,
                              crop: Crop | None = None) -> np.ndarray:
        """Images (N,H,W,3) of the reference body posed by its joints' transforms (N,J,4,4)
        in the body frame (`BodyModel.joint_transforms`); `full`, `out` and `crop` as in
        `robot_frames`."""
        if self._skin is None:
            raise ValueError("no reference skin bound (bind_reference_skin)")
        transforms = np.asarray(transforms, dtype=np.float64)
        self._target(out, len(transforms), full, crop)
        self._ctx.make_current()
        cam = self.camera(view)
        frames = []
        for i, pose in enumerate(self._skin.bone_poses(transforms)):
            self._skin.set_pose(*pose)
            frames.append(self._draw(self._skin.model, self._skin.data, self._skin_scene,
                                     self._skin_ctx, cam, None if out is None else out[i], crop))
        return self._finish(frames, full, out)

    def close(self) -> None:
        """Free GL resources now: EGL teardown at interpreter exit prints errors otherwise."""
        if self._ctx is None:
            return
        self._ctx.make_current()
        for ctx in self._contexts:
            ctx.free()
        self._contexts.clear()
        self._ctx.free()
        self._ctx = None

    def __enter__(self) -> "SceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _black(flat: np.ndarray) -> np.ndarray:
    """Pixels (N,3) still at the clear colour (pure black, which no lit surface here reaches)."""
    return (flat[:, 0] | flat[:, 1] | flat[:, 2]) == 0


def _fill_background_gl(rgb: np.ndarray) -> bool:
    """Paint the background colour where nothing was drawn, in GL: one full-screen quad at the
    cleared depth (MuJoCo clears depth to 0 and draws with GL_GEQUAL, reversed z), ~10× cheaper
    on software GL than the same fill in NumPy after the read-back. False when it cannot run
    (no PyOpenGL); the caller then fills after reading."""
    try:
        from OpenGL import GL
    except Exception:  # noqa: BLE001 - the NumPy fill is the fallback
        return False
    try:
        GL.glPushAttrib(GL.GL_ALL_ATTRIB_BITS)
        GL.glMatrixMode(GL.GL_PROJECTION)
        GL.glPushMatrix()
        GL.glLoadIdentity()
        GL.glMatrixMode(GL.GL_MODELVIEW)
        GL.glPushMatrix()
        GL.glLoadIdentity()
        for cap in (GL.GL_LIGHTING, GL.GL_TEXTURE_2D, GL.GL_BLEND, GL.GL_CULL_FACE, GL.GL_FOG):
            GL.glDisable(cap)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_GEQUAL)  # passes only where the depth is still the cleared 0
        GL.glDepthMask(GL.GL_FALSE)
        GL.glColor3ub(int(rgb[0]), int(rgb[1]), int(rgb[2]))
        GL.glBegin(GL.GL_QUADS)
        for x, y in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            GL.glVertex3f(x, y, 0.0)
        GL.glEnd()
        GL.glMatrixMode(GL.GL_PROJECTION)
        GL.glPopMatrix()
        GL.glMatrixMode(GL.GL_MODELVIEW)
        GL.glPopMatrix()
        GL.glPopAttrib()
    except Exception:  # noqa: BLE001 - e.g. a core-profile context: fill after reading
        return False
    return True


class _MeshModel:
    """A model holding one visual mesh at the world origin whose vertices we overwrite."""

    def __init__(self, faces: np.ndarray, rest_vertices: np.ndarray, cfg: RenderConfig,
                 fovy: float, size: tuple[int, int]) -> None:
        spec = _lit_spec(cfg, fovy, size)
        mesh = spec.add_mesh(name="reference")
        mesh.uservert = np.asarray(rest_vertices, dtype=np.float64).ravel().tolist()
        mesh.userface = np.asarray(faces, dtype=np.int64).ravel().tolist()
        # one normal per vertex, indexed like the vertices: each frame writes them as one block
        mesh.usernormal = vertex_normals(np.asarray(rest_vertices, dtype=np.float64),
                                         np.asarray(faces, dtype=np.int64)).ravel().tolist()
        mesh.userfacenormal = mesh.userface
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname="reference",
                                contype=0, conaffinity=0, rgba=list(cfg.reference_rgba))
        self.model = spec.compile()
        self.faces = np.asarray(faces, dtype=np.int64)
        mid = 0
        self.mesh_id = mid
        adr, num = self.model.mesh_vertadr[mid], self.model.mesh_vertnum[mid]
        if num != len(rest_vertices):
            raise ValueError(f"MuJoCo kept {num} of {len(rest_vertices)} mesh vertices")
        self._verts = slice(adr, adr + num)
        fadr, fnum = self.model.mesh_faceadr[mid], self.model.mesh_facenum[mid]
        self._face_normal = self.model.mesh_facenormal[fadr:fadr + fnum]
        self._face = self.model.mesh_face[fadr:fadr + fnum]
        self._nadr = self.model.mesh_normaladr[mid]
        # Normals are indexed like the vertices (as written above) unless the compiler chose
        # otherwise; then each frame scatters them through the face-normal indices.
        self._aligned = bool(self.model.mesh_normalnum[mid] == num
                             and np.array_equal(self._face_normal, self._face))
        # vertex normal = Σ adjacent face normals (area-weighted), one sparse product a frame
        f = self._face.astype(np.int64)
        self._incidence = scipy.sparse.csr_matrix(
            (np.ones(f.size), (f.ravel(), np.repeat(np.arange(len(f)), 3))), shape=(num, len(f)))
        # The compiler recentres meshes and compensates in the geom pose; we write world
        # coordinates, so put the geom back at the origin.
        self.model.geom_pos[0] = 0.0
        self.model.geom_quat[0] = (1.0, 0.0, 0.0, 0.0)
        self.data = mujoco.MjData(self.model)
        mujoco.mj_kinematics(self.model, self.data)

    def set_vertices(self, world_vertices: np.ndarray, ctx: mujoco.MjrContext) -> None:
        v = np.asarray(world_vertices, dtype=np.float64)
        f = self._face
        normals = self._incidence @ np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        self.model.mesh_vert[self._verts] = v
        if self._aligned:
            self.model.mesh_normal[self._nadr:self._nadr + len(v)] = normals
        else:
            self.model.mesh_normal[self._nadr + self._face_normal.ravel()] = normals[f.ravel()]
        mujoco.mjr_uploadMesh(self.model, ctx, self.mesh_id)


def _lit_spec(cfg: RenderConfig, fovy: float, size: tuple[int, int]) -> mujoco.MjSpec:
    """An empty model with the reference body's camera, buffer size and lights."""
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = size
    spec.visual.quality.offsamples = 0
    spec.visual.quality.shadowsize = _SHADOW_SIZE
    spec.visual.global_.fovy = fovy
    spec.visual.headlight.diffuse = [0.6, 0.6, 0.6]
    spec.visual.headlight.ambient = [0.1, 0.1, 0.1]
    spec.worldbody.add_light(pos=[1, 0, 3.5], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    return spec


class _SkinModel:
    """The reference body as a MuJoCo skin: one mocap body per bone that moves any drawn vertex,
    bound at the rest joints; MuJoCo blends the vertices and their normals each frame.

    Bone j maps a rest vertex v (body frame) to R_j (v − b_j) + t_j; with the body→world map
    p ↦ s·A p + c that is (A R_j)(s v − s b_j) + (s A t_j + c): the skin holds s·v, bind s·b_j,
    and each mocap body gets the rotation A R_j at s A t_j + c."""

    def __init__(self, faces: np.ndarray, rest_vertices: np.ndarray, weights: np.ndarray,
                 bind: np.ndarray, scale: float, rotation: np.ndarray, offset: np.ndarray,
                 cfg: RenderConfig, fovy: float, size: tuple[int, int]) -> None:
        weights = np.asarray(weights, dtype=np.float64)
        self.bones = np.flatnonzero((weights > 0).any(axis=0))
        self.scale, self.rotation, self.offset = float(scale), rotation, offset
        spec = _lit_spec(cfg, fovy, size)
        for j in self.bones:
            spec.worldbody.add_body(name=f"bone{j}", mocap=True)
        skin = spec.add_skin(name="reference")
        skin.vert = (self.scale * np.asarray(rest_vertices, np.float64)).ravel().tolist()
        skin.face = np.asarray(faces, dtype=np.int64).ravel().tolist()
        skin.rgba = list(cfg.reference_rgba)
        skin.bodyname = [f"bone{j}" for j in self.bones]
        skin.bindpos = (self.scale * np.asarray(bind, np.float64)[self.bones]).ravel().tolist()
        skin.bindquat = np.tile([1.0, 0.0, 0.0, 0.0], len(self.bones)).tolist()
        skin.vertid = [np.flatnonzero(weights[:, j] > 0).tolist() for j in self.bones]
        skin.vertweight = [weights[weights[:, j] > 0, j].tolist() for j in self.bones]
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        offsets = np.linalg.norm(np.asarray(rest_vertices, np.float64)[:, None]
                                 - np.asarray(bind, np.float64)[self.bones], axis=2)  # (K,B)
        self.radii = self.scale * np.where(weights[:, self.bones] > 0, offsets, 0.0).max(axis=0)

    def bone_poses(self, transforms: np.ndarray):
        """Per frame (mocap positions (B,3), quaternions (B,4)) of joint transforms (N,J,4,4)."""
        tf = transforms[:, self.bones]
        rot = np.einsum("ab,tjbc->tjac", self.rotation, tf[..., :3, :3])
        pos = np.einsum("ab,tjb->tja", self.scale * self.rotation, tf[..., :3, 3]) + self.offset
        quat = np.empty(rot.shape[:2] + (4,))
        for t in range(len(rot)):
            for j in range(rot.shape[1]):
                mujoco.mju_mat2Quat(quat[t, j], rot[t, j].ravel())
        return zip(pos, quat)

    def bone_spheres(self, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per bone, a sphere about its posed joint (N,B,3) of radius (B,) the farthest scaled
        rest offset of a vertex it moves: bone j alone would put each of its vertices inside
        its sphere, and a blended vertex is a convex combination of such positions, so its
        image lies in the box of the spheres' images."""
        pos = (np.einsum("ab,tjb->tja", self.scale * self.rotation,
                         transforms[:, self.bones][..., :3, 3]) + self.offset)
        return pos, self.radii

    def set_pose(self, pos: np.ndarray, quat: np.ndarray) -> None:
        self.data.mocap_pos[:] = pos
        self.data.mocap_quat[:] = quat
        mujoco.mj_kinematics(self.model, self.data)
