"""Offscreen rendering: image sizes, the robot and reference where the cameras should see them,
deterministic bytes, keyframes at extrema, the comparison sheet and the preview."""

import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from embody.config import load_config
from embody.config.render import RenderConfig
from embody.errors import ConfigError
from embody.render import SceneRenderer, comparison_sheet, png_bytes, select_keyframes, write_preview
from embody.robot import load_robot

W, H = 96, 72
#: A fixed camera, so the expected image positions below are known in advance.
CFG = RenderConfig(width=W, height=H, lookat=(0.1, 0.0, 0.15), camera_distance=1.2)
BACKGROUND = np.round(np.asarray(CFG.background_rgb) * 255).astype(int)


def _cube(center, half=0.05):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * half
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return corners + np.asarray(center, float), faces


@pytest.fixture(scope="module")
def robot():
    return load_robot()


@pytest.fixture(scope="module")
def renderer(robot):
    verts, faces = _cube((0, 0, 0))
    r = SceneRenderer(robot, CFG, faces, verts)
    yield r
    r.close()


def _mask(img):
    return np.abs(img.astype(int) - BACKGROUND).max(axis=-1) > 0  # not the background colour


def _bbox(mask):
    ys, xs = np.nonzero(mask)
    return xs.min(), xs.max(), ys.min(), ys.max()


def test_robot_is_visible_inside_the_expected_box(robot, renderer):
    imgs = renderer.robot_frames(np.stack([robot.tpose, np.zeros(robot.n_joints)]))
    assert imgs.shape == (2, H, W, 3) and imgs.dtype == np.uint8
    tpose, rest = _mask(imgs[0]), _mask(imgs[1])
    for m in (tpose, rest):
        assert m[H // 2 - 4:H // 2 + 4, W // 2 - 4:W // 2 + 4].mean() > 0.5  # torso at the centre
        assert not m[:3, :3].any() and not m[-3:, -3:].any()  # corners stay background
        assert 0.05 < m.mean() < 0.6
    x0, x1, _, _ = _bbox(tpose)
    r0, r1, _, _ = _bbox(rest)
    assert (x1 - x0) > 1.5 * (r1 - r0)  # T-pose arms reach far out sideways
    assert abs((x0 + x1) / 2 - W / 2) < 4  # and symmetric about the image centre


def test_left_arm_up_shows_on_image_right_and_side_view_differs(robot, renderer):
    q = robot.tpose.copy()
    q[robot.joint_index("left_shoulder_roll_joint")] = 2.6  # raise the left arm
    up = _mask(renderer.robot_frames(q[None])[0])
    base = _mask(renderer.robot_frames(robot.tpose[None])[0])
    changed = up ^ base
    ys, xs = np.nonzero(changed)
    assert xs.mean() > W / 2  # the robot faces the camera: its left is the image's right
    assert ys[up[ys, xs]].mean() < H / 2  # new pixels are above the centre
    side = _mask(renderer.robot_frames(robot.tpose[None], view="side")[0])
    assert not np.array_equal(side, base)
    x0, x1, _, _ = _bbox(side)
    assert x1 - x0 < (_bbox(base)[1] - _bbox(base)[0]) / 2  # arms point at the side camera


def test_reference_mesh_lines_up_with_the_torso_frame(renderer):
    # a cube 30 cm to the robot's left of the look-at point, at its height
    verts, _ = _cube((0.1, 0.3, 0.15))
    img = renderer.reference_frames(verts[None])[0]
    m = _mask(img)
    assert m.any()
    ys, xs = np.nonzero(m)
    assert xs.mean() > 0.65 * W and abs(ys.mean() - H / 2) < 0.15 * H
    verts2, _ = _cube((0.1, -0.3, 0.15))
    xs2 = np.nonzero(_mask(renderer.reference_frames(verts2[None])[0]))[1]
    assert xs2.mean() < 0.35 * W


def test_same_input_same_png_bytes(robot, renderer):
    a = png_bytes(renderer.robot_frames(robot.tpose[None])[0])
    b = png_bytes(renderer.robot_frames(robot.tpose[None])[0])
    assert a == b


def test_keyframes_at_holds_and_extremes():
    t = np.arange(90)
    # left wrist: still at x=0 until 20, moves to x=1 by 40, holds to 60, returns by 80
    x = np.interp(t, [0, 20, 40, 60, 80, 89], [0, 0, 1, 1, 0, 0])
    pos = np.zeros((90, 2, 3))
    pos[:, 0, 0] = x
    pos[:, 1, 2] = 0.3 * np.sin(t / 89 * np.pi)  # right wrist: one up-down swing, peak at the middle
    k = select_keyframes(pos, 4)
    assert len(k) == 4 and np.all(np.diff(k) > 0)
    assert any(40 <= i <= 60 for i in k)  # the hold at the extreme position
    assert np.array_equal(k, select_keyframes(pos, 4))
    assert len(select_keyframes(pos[:3], 8)) == 3
    many = select_keyframes(pos, 30)
    assert len(many) == 30 and len(set(many.tolist())) == 30


def test_sheet_layout_and_preview_files(tmp_path):
    k = 3
    rows = [("human", np.full((k, H, W, 3), 80, np.uint8)), ("robot", np.full((k, H, W, 3), 160, np.uint8))]
    sheet = comparison_sheet(rows, ["f0", "f5", "f9"], title="t")
    assert sheet.size[0] > k * W and sheet.size[1] > 2 * H
    arr = np.asarray(sheet)
    for value in (80, 160):  # every tile pasted whole (a few label pixels may share the value)
        assert k * W * H <= (arr == value).all(axis=-1).sum() < k * W * H + 100
    assert png_bytes(sheet) == png_bytes(comparison_sheet(rows, ["f0", "f5", "f9"], title="t"))
    frames = np.random.default_rng(0).integers(0, 255, (6, H, W, 3), dtype=np.uint8)
    gif = write_preview(frames, tmp_path / "p", 10, "gif")
    assert gif.suffix == ".gif" and Image.open(gif).n_frames == 6
    mp4 = write_preview(frames, tmp_path / "p", 10, "mp4")
    assert mp4.suffix == ".mp4" and mp4.read_bytes()[4:8] == b"ftyp"


def test_render_config_validation():
    with pytest.raises(ConfigError, match="render.views"):
        load_config(sets=["render.views=[front, front]"])
    with pytest.raises(ConfigError, match="render.width"):
        load_config(sets=["render.width=0"])


def test_background_painted_in_gl_equals_the_numpy_fill(robot, renderer):
    q = np.stack([robot.tpose, np.zeros(robot.n_joints)])
    gl = renderer.robot_frames(q, full=True)
    assert renderer._gl_fill is True  # the GL fill ran and left no clear colour
    renderer._gl_fill = False
    try:
        filled = renderer.robot_frames(q, full=True)
    finally:
        renderer._gl_fill = None
    assert np.array_equal(gl, filled)
    assert (gl[:, 0, 0] == BACKGROUND).all()


def test_decimated_robot_meshes_keep_the_silhouette(robot, renderer):
    q = robot.tpose.copy()
    q[robot.joint_index("left_elbow_joint")] = 0.3
    fast = _mask(renderer.robot_frames(q[None])[0])  # any robot pixel: shading may differ
    whole = CFG.model_copy(update={"mesh_cell_m": 0.0, "robot_body_cell_m": 0.0})
    with SceneRenderer(robot, whole) as full_renderer:
        full = _mask(full_renderer.robot_frames(q[None])[0])
    assert (fast & full).sum() / (fast | full).sum() > 0.95
    # the torso and arms on the coarser grid, the hands on the fine one
    faces = {}
    for cell in (None, CFG.robot_body_cell_m):
        model = SceneRenderer(robot, CFG.model_copy(update={"robot_body_cell_m": cell}))
        m = model._model
        faces[cell] = tuple(
            m.mesh_facenum[m.geom_dataid[(m.geom_bodyid == m.body(b).id) & (m.geom_dataid >= 0)]].sum()
            for b in ("torso_link", "left_elbow_link", "left_wrist_yaw_link",
                      "right_hand_index_1_link"))
        model.close()
    coarse, fine = faces[CFG.robot_body_cell_m], faces[None]
    assert coarse[0] < 0.6 * fine[0] and coarse[1] < fine[1]
    assert coarse[2:] == fine[2:]


# --- the render step: preview in real time, sheet frames reused, skinned decimated body ---

@pytest.fixture(scope="module")
def fitted(robot):
    from embody.body import load_body_model
    from embody.config.ik import IKConfig
    from embody.retarget import shape_fit
    body = load_body_model()
    return body, shape_fit(robot, body, IKConfig())


def _wave(robot, n: int, fps: float):
    from embody.motion import Motion
    s = np.linspace(0, 1, n)
    pose = np.zeros((n, 55, 3), np.float32)
    pose[:, 16, 2], pose[:, 17, 2] = -1.0 + 0.8 * s, 1.0 - 0.8 * s  # shoulders: arms rise
    q = np.tile(robot.tpose, (n, 1))
    q[:, robot.joint_index("left_shoulder_roll_joint")] += 0.8 * s
    return Motion(pose=pose, transl=np.zeros((n, 3)), betas=np.zeros(10), fps=fps), q


def test_preview_plays_in_real_time_at_480px_and_sheet_reuses_its_frames(robot, fitted):
    import imageio_ffmpeg

    from embody.render.compare import open_renderer, render_comparison
    from embody.render.record import SequenceRender, render_sequence
    body, fit = fitted
    motion, q = _wave(robot, 14, 24.0)
    keys = np.array([0, 5, 13])  # frame 5 is not one of the 12 fps preview's
    for cfg, shown in ((RenderConfig(keyframes=3, preview_fps=None, preview_crop=False), 14),
                       (RenderConfig(keyframes=3, preview_fps=12.0), 7)):
        out = render_sequence(motion, body, fit, robot, q, keys, cfg, "t")
        assert out.preview_suffix == ".mp4"
        path = Path(tempfile.mkdtemp()) / "p.mp4"
        path.write_bytes(out.preview)
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        assert sum(1 for _ in reader) == shown  # every source frame, or every 2nd
        assert meta["fps"] == pytest.approx(24.0 * shown / 14)  # played in real time
        w, h = cfg.supersample * cfg.width, cfg.supersample * cfg.height
        if cfg.preview_crop:  # only what the bodies reach, at the drawn scale
            assert meta["size"][0] < 2 * w and meta["size"][1] <= h
            assert meta["size"][0] % 4 == 0 and meta["size"][1] % 2 == 0
        else:
            assert meta["size"] == (2 * w, h) and h >= 480
        # the sheet (first view taken from the preview's pass) matches one drawn directly
        sheet = np.asarray(Image.open(io.BytesIO(out.sheet_png)))
        with open_renderer(robot, body, fit, cfg) as renderer:
            direct = render_comparison(renderer, cfg, keys, motion.fps, q,
                                       motion=motion).sheet_png("t")
        assert np.array_equal(sheet, np.asarray(Image.open(io.BytesIO(direct))))
        again = SequenceRender.from_arrays(out.to_arrays(), out.to_attrs())
        assert again.preview == out.preview and again.sheet_png == out.sheet_png


def test_a_kept_renderer_draws_the_same_bytes_and_opens_once(robot, fitted, monkeypatch):
    from embody.render import record
    body, fit = fitted
    cfg = RenderConfig(keyframes=2, preview_fps=12.0)
    waves = [_wave(robot, 6, 24.0), _wave(robot, 9, 30.0)]
    waves[1][1][:, robot.joint_index("right_elbow_joint")] += 0.3  # another pose
    keys = np.array([0, 5])
    fresh = [record.render_sequence(m, body, fit, robot, q, keys, cfg, "t").to_arrays()
             for m, q in waves]
    opened, closed = [], []
    real_open = record.open_renderer

    def counting_open(*args):
        renderer = real_open(*args)
        real_close = renderer.close
        renderer.close = lambda: (closed.append(renderer), real_close())
        opened.append(renderer)
        return renderer
    monkeypatch.setattr(record, "open_renderer", counting_open)
    with record.kept_renderer():
        kept = [record.render_sequence(m, body, fit, robot, q, keys, cfg, "t").to_arrays()
                for m, q in waves + waves[:1]]
        assert len(opened) == 1 and not closed  # one renderer for the three sequences
        other = RenderConfig(keyframes=2, preview_fps=12.0, width=200)
        record.render_sequence(waves[0][0], body, fit, robot, waves[0][1], keys, other, "t")
        assert len(opened) == 2 and closed == opened[:1]  # another config: the old one closed
    assert closed == opened  # closed at the block's end
    for a, b in zip(fresh + fresh[:1], kept):
        assert a.keys() == b.keys()
        assert all(np.array_equal(a[k], b[k]) for k in a)
    record.render_sequence(waves[0][0], body, fit, robot, waves[0][1], keys, cfg, "t")
    assert len(closed) == len(opened) == 3  # outside the block: opened and closed each time


def test_preview_crop_holds_both_bodies_and_draws_the_same_pixels(robot, fitted):
    from embody.render.compare import draw_reference, open_renderer, preview_crop
    body, fit = fitted
    motion, q = _wave(robot, 8, 30.0)
    frames = np.arange(8)
    with open_renderer(robot, body, fit, RenderConfig()) as renderer:
        w, h = renderer.size
        crop = preview_crop(renderer, motion, q, frames, "front")
        assert crop is not None
        x0, y0, x1, y1 = crop
        assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h and (x1 - x0) * (y1 - y0) < 0.8 * w * h
        assert (x1 - x0) % 2 == 0 and (y1 - y0) % 2 == 0
        whole = [draw_reference(renderer, motion, frames, "front", full=True),
                 renderer.robot_frames(q, "front", full=True)]
        parts = [draw_reference(renderer, motion, frames, "front", full=True, crop=crop),
                 renderer.robot_frames(q, "front", full=True, crop=crop)]
        for full, part in zip(whole, parts):
            outside = _mask(full)
            outside[:, y0:y1, x0:x1] = False
            assert _mask(full).sum() > 1000 and not outside.any()  # nothing cut off
            diff = np.abs(part.astype(int) - full[:, y0:y1, x0:x1].astype(int)).max(axis=-1)
            assert part.shape == (8, y1 - y0, x1 - x0, 3) and (diff > 2).mean() < 1e-3
        with pytest.raises(ValueError, match="crop"):
            renderer.robot_frames(q[:1], "front", full=True, crop=(0, 0, w + 2, h))


def test_pixel_bounds_hold_the_spheres():
    from embody.render.framing import pixel_bounds, project
    from embody.robot import load_robot
    model = load_robot().model
    rng = np.random.default_rng(1)
    centres = rng.uniform(-0.4, 0.4, (5, 3)) + [0.0, 0.0, 1.0]
    radii = rng.uniform(0.02, 0.15, 5)
    args = (model, np.array([0.0, 0.0, 1.0]), 2.0, 150.0, -5.0)
    box = pixel_bounds(*args, centres, radii, 640, 480)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    surface = (centres[:, None] + radii[:, None, None] * dirs).reshape(-1, 3)
    uv = project(*args, surface, 640, 480)
    inside = (uv[:, 0] >= box[0]) & (uv[:, 0] <= box[2]) & (uv[:, 1] >= box[1]) & (uv[:, 1] <= box[3])
    assert inside.all()
    # and not much more: the box is within a few pixels of the sampled extent
    assert box[0] >= uv[:, 0].min() - 12 and box[2] <= uv[:, 0].max() + 12
    az, el = np.radians(150.0), np.radians(-5.0)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    eye = np.array([0.0, 0.0, 1.0]) - 2.0 * forward
    assert pixel_bounds(*args, eye[None], 0.1, 640, 480) is None  # reaches behind the camera


def test_reference_skin_draws_what_the_skinned_vertices_draw(robot, fitted):
    """The bound MuJoCo skin (bone poses) and the re-uploaded mesh (vertices) give the same
    picture up to edge pixels (float32 blending, MuJoCo's own normals)."""
    from embody.render.compare import draw_reference, open_renderer
    body, fit = fitted
    motion, _ = _wave(robot, 6, 30.0)
    frames = np.array([0, 5])
    with open_renderer(robot, body, fit, RenderConfig()) as renderer:
        assert renderer.posed
        for view in ("front", "side"):
            posed = draw_reference(renderer, motion, frames, view)
            meshed = renderer.reference_frames(renderer.skin(motion, frames), view)
            a, b = _mask(posed), _mask(meshed)
            assert a.sum() > 1000 and (a & b).sum() / (a | b).sum() > 0.99
            diff = np.abs(posed.astype(int) - meshed.astype(int)).max(axis=-1)
            assert (diff > 8).mean() < 0.01
    # a body→torso map that is not a similarity: no skin, the vertex path, no preview crop
    import dataclasses

    from embody.render.compare import preview_crop
    mirrored = dataclasses.replace(fit, rotation=fit.rotation @ np.diag([1.0, 1.0, -1.0]))
    with open_renderer(robot, body, mirrored, RenderConfig()) as renderer:
        assert not renderer.posed
        assert _mask(draw_reference(renderer, motion, frames, "front")).sum() > 1000
        assert preview_crop(renderer, motion, np.tile(robot.tpose, (6, 1)), frames, "front") is None
    # and the renderer refuses to bind one
    with open_renderer(robot, body, fit, RenderConfig()) as renderer:
        with pytest.raises(ValueError, match="similarity|scale times a rotation"):
            renderer.bind_reference_skin(np.zeros((len(renderer.reference_keep), 3)),
                                         np.ones((len(renderer.reference_keep), 1)),
                                         np.zeros((1, 3)), 1.0, np.diag([1.0, 1.0, -1.0]),
                                         np.zeros(3))


def test_preview_frames_follow_the_source_rate_or_the_configured_one():
    from embody.render.compare import preview_frames
    frames, rate = preview_frames(RenderConfig(preview_fps=None), 90, 30.0)
    assert len(frames) == 90 and rate == pytest.approx(30.0)
    frames, rate = preview_frames(RenderConfig(), 90, 30.0)  # default 15 fps: every 2nd frame
    assert len(frames) == 45 and rate == pytest.approx(15.0)
    assert set(np.diff(frames)) <= {2, 3}
    frames, rate = preview_frames(RenderConfig(preview_fps=10.0), 90, 30.0)
    assert len(frames) == 30 and rate == pytest.approx(10.0)
    frames, rate = preview_frames(RenderConfig(preview_fps=None, preview_max_frames=45), 90, 30.0)
    assert len(frames) == 45 and rate == pytest.approx(15.0)  # still real time


def test_decimated_reference_keeps_pieces_apart_and_the_silhouette(robot, fitted):
    from embody.render.compare import open_renderer
    from embody.render.scene import cluster_faces
    # two touching triangles of different pieces/bones never merge, however coarse the grid
    tri = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0]], float)
    verts = np.concatenate([tri, tri + [0, 0, 1e-3]])  # each vertex 1 mm from its twin
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    keep, kept = cluster_faces(verts, faces, 0.05)
    assert len(keep) == 6 and len(kept) == 2
    keep, kept = cluster_faces(verts, faces, 0.0)
    assert np.array_equal(keep, np.arange(6)) and np.array_equal(kept, faces)
    # per-vertex cells: a fine (here: zero) cell keeps its vertices, a coarse one merges
    grid = np.array([[0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0], [0.1, 0, 0], [0, 0.1, 0]], float)
    fan = np.array([[0, 1, 2], [0, 3, 4], [1, 3, 4]])
    keep, kept = cluster_faces(grid, fan, np.array([0.05, 0.05, 0.05, 0.0, 0.0]))
    assert np.array_equal(keep, [0, 3, 4]) and len(kept) == 1  # 1 and 2 merged into 0
    keep, kept = cluster_faces(grid, fan, np.array([0.0, 0.0, 0.0, 0.05, 0.05]))
    assert len(keep) == 5 and len(kept) == 3
    body, fit = fitted
    motion, _ = _wave(robot, 2, 30.0)
    masks = []
    full = RenderConfig(reference_cell_m=0.0, reference_body_cell_m=0.0)
    for cfg in (full, RenderConfig()):
        with open_renderer(robot, body, fit, cfg) as renderer:
            assert renderer.skin.exact  # sparse skinning of only the drawn vertices is exact here
            masks.append(_mask(renderer.reference_frames(renderer.skin(motion, [1]))[0]))
            drawn = len(renderer.reference_keep)
    assert drawn < 0.6 * len(body.skin_weights)  # the default draws far fewer vertices
    assert (masks[0] & masks[1]).sum() / (masks[0] | masks[1]).sum() > 0.97


def test_reference_hands_keep_the_fine_cell(fitted):
    from embody.render.compare import hand_bones, reference_cells
    body, _ = fitted
    hands = hand_bones(body)
    names = [body.joint_names[j] for j in hands]
    assert {"left_wrist", "right_wrist", "left_index3", "right_thumb1"} <= set(names)
    assert not {"left_elbow", "head", "spine3"} & set(names)
    cfg = RenderConfig()
    cells = reference_cells(body, cfg)
    on_hand = np.isin(np.asarray(body.skin_weights).argmax(axis=1), hands)
    assert on_hand.any() and (~on_hand).any()
    assert np.all(cells[on_hand] == cfg.reference_cell_m)
    assert np.all(cells[~on_hand] == cfg.reference_body_cell_m)
    same = reference_cells(body, RenderConfig(reference_body_cell_m=None))
    assert np.all(same == cfg.reference_cell_m)


def test_reference_legs_are_left_out_with_the_robots(fitted):
    from embody.render.compare import drawn_faces, leg_bones
    body, _ = fitted
    assert {body.joint_names[j] for j in leg_bones(body)} >= {"left_hip", "right_knee", "left_foot"}
    faces = np.asarray(body.faces)
    assert np.array_equal(drawn_faces(body, RenderConfig(upper_body=False)), faces)
    upper = drawn_faces(body, RenderConfig())
    bones = np.asarray(body.skin_weights).argmax(axis=1)
    on_legs = np.isin(bones, leg_bones(body))
    assert 0.1 * len(faces) < len(faces) - len(upper) < 0.5 * len(faces)
    assert not on_legs[upper].all(axis=1).any()  # no face left wholly on the legs
    on_hand = (bones[faces] == body.joint_names.index("left_wrist")).all(axis=1)
    kept = {tuple(f) for f in upper.tolist()}
    assert on_hand.any() and all(tuple(f) in kept for f in faces[on_hand].tolist())


def test_downsample_is_the_rounded_block_mean():
    from embody.render.scene import downsample

    rng = np.random.default_rng(0)
    x = rng.integers(0, 256, (2, 12, 18, 3), dtype=np.uint8)
    assert downsample(x, 1) is x
    for f in (2, 3):
        s = x.reshape(2, 12 // f, f, 18 // f, f, 3).astype(np.int64).sum(axis=(2, 4))
        got = downsample(x, f)
        assert got.dtype == np.uint8 and np.array_equal(got, (s + f * f // 2) // (f * f))
