"""Synthetic signing: determinism, metadata, real interpenetration, smoothness, CLI."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embody.body import load_body_model
from embody.cli import main
from embody.io import load, load_dataset
from embody.synth import GENERATOR_VERSION, default_dataset, generate_dataset
from embody.synth.artifacts import PENETRATIONS

KINDS = {"hand_torso", "hand_face", "hand_hand", "finger_overlap", "jitter"}


@pytest.fixture(scope="module")
def default_set(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    return data, default_dataset(data)


@pytest.fixture(scope="module")
def motions(default_set):
    return [load(p) for p in sorted(default_set[1].glob("seq_*.npz"))]


def test_default_dataset_layout_and_reuse(default_set):
    data, root = default_set
    assert root == data / "synth-n24-s0"
    files = sorted(root.glob("seq_*.npz"))
    assert [f.name for f in files] == [f"seq_{i:03d}.npz" for i in range(24)]
    assert [p.name for p in data.iterdir()] == ["synth-n24-s0"]  # no temp folder left behind
    stamp = files[0].stat().st_mtime_ns
    assert default_dataset(data) == root and files[0].stat().st_mtime_ns == stamp  # not regenerated
    ds = load_dataset(root)
    assert ds.ids == [f"seq_{i:03d}" for i in range(24)]
    assert len(load_dataset(root / "manifest.csv")) == 24


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    a = generate_dataset(tmp_path / "a", n=2, seed=5)
    b = generate_dataset(tmp_path / "b", n=2, seed=5)
    c = generate_dataset(tmp_path / "c", n=2, seed=6)
    for pa, pb, pc in zip(a, b, c):
        assert pa.read_bytes() == pb.read_bytes()
        assert pa.read_bytes() != pc.read_bytes()
    assert (tmp_path / "a/manifest.csv").read_bytes() == (tmp_path / "b/manifest.csv").read_bytes()


def test_sequences_are_sign_like_and_record_metadata(motions):
    for m in motions:
        assert 90 <= m.num_frames <= 180 and m.fps == 30.0
        assert m.source.hand_convention == "absolute" and m.source.format == "embody"
        assert np.all(m.transl == 0) and np.all(m.betas == 0)
        meta = m.meta
        assert meta["generator"] == GENERATOR_VERSION and meta["seed"] == 0
        assert 3 <= len(meta["gloss"]) <= 6 and meta["text"] == " ".join(meta["gloss"])
        for art in meta["artifacts"]:
            assert art["kind"] in KINDS and 0 <= art["start"] < art["end"] <= m.num_frames
        # hands move through several handshapes: finger poses vary over time
        assert np.ptp(m.pose[:, 40:55], axis=0).max() > 0.5
    with_pen = [m for m in motions if any(a["kind"] in PENETRATIONS for a in m.meta["artifacts"])]
    assert len(with_pen) >= 0.6 * len(motions)  # most, ...
    assert len(with_pen) < len(motions)         # ... not all
    kinds = {a["kind"] for m in motions for a in m.meta["artifacts"]}
    assert kinds == KINDS
    assert any(s["hands"] != "one" for m in motions for s in m.meta["signs"])  # two-handed signs


def test_transitions_are_smooth_outside_jitter(motions):
    from scipy.spatial.transform import Rotation

    for m in motions[:8]:
        noisy = np.zeros(m.num_frames, bool)
        for a in m.meta["artifacts"]:
            if a["kind"] in ("jitter", "finger_overlap"):
                noisy[max(a["start"] - 1, 0):a["end"] + 1] = True
        for joint in (16, 17, 18, 19):
            r = Rotation.from_rotvec(m.pose[:, joint].astype(np.float64))
            step = np.degrees((r[1:] * r[:-1].inv()).magnitude())
            assert step[~noisy[1:]].max() < 20.0, (m.meta["index"], joint)


def _penetration(body, geometry, pose, hand_part, others):
    """Deepest signed distance (m, <0 inside) over frames of a hand part's skinned vertices in
    other parts' convex pieces."""
    p = torch.as_tensor(pose, dtype=torch.float32)
    verts = body.vertices(p, torch.zeros(10)).numpy()
    transforms = body.joint_transforms(p, torch.zeros(10)).numpy()
    mask = body.vertex_parts == body.part_names.index(hand_part)
    deepest = 0.0
    for piece in geometry:
        if body.part_names[piece.part] in others:
            for pts, tf in zip(verts[:, mask], transforms[:, piece.joint]):
                local = (pts - tf[:3, 3]) @ tf[:3, :3]
                sd = (local @ piece.planes[:, :3].T + piece.planes[:, 3]).max(axis=1)
                deepest = min(deepest, float(sd.min()))
    return deepest


def test_injected_penetrations_really_penetrate_the_skinned_mesh(motions):
    body = load_body_model()
    geometry = body.collision_geometry(np.zeros(10))
    others = {"hand_torso": ("spine1", "spine3"), "hand_face": ("head",), "hand_hand": ("left_wrist",)}
    checked = 0
    for m in motions[:8]:
        for art in m.meta["artifacts"]:
            if art["kind"] not in others:
                continue
            frames = np.linspace(art["start"], art["end"] - 1, 3).round().astype(int)
            depth = _penetration(body, geometry, m.pose[frames], "right_wrist", others[art["kind"]])
            assert depth < -0.01, (m.meta["index"], art)
            checked += 1
    assert checked >= 6


def _finger_joints(pose_left_hand):
    from embody.synth.kinematics import _skeleton

    skel = _skeleton()
    pose = np.zeros((1, 55, 3))
    pose[0, 25:40] = pose_left_hand
    world = skel.forward_skeleton(pose[:, 1:22], pose[:, 22:25], pose[:, 25:55],
                                  shape=np.zeros(10))[0, :, :3, 3]
    return {name: world[i] for i, name in enumerate(skel.joint_names)}


def test_handshapes_and_finger_overlap_geometry():
    from embody.synth.handshapes import finger_overlap, handshape

    flat, spread, fist = (_finger_joints(handshape(n, "left")) for n in ("flat", "spread", "fist"))
    width = lambda j: np.linalg.norm(j["L_Index3"] - j["L_Pinky3"])  # noqa: E731
    assert width(spread) > width(flat) + 0.02                  # spread fans the fingers out
    reach = lambda j: j["L_Middle3"][0] - j["L_Wrist"][0]       # noqa: E731
    assert reach(fist) < reach(flat) - 0.06                     # a fist is short
    bad = _finger_joints(finger_overlap("left", 0.5))
    # index and middle middle-joints sit side by side in a flat hand, on top of each other here
    assert abs(flat["L_Index2"][2] - flat["L_Middle2"][2]) > 0.02
    assert abs(bad["L_Index2"][2] - bad["L_Middle2"][2]) < 0.008
    # right hands are the mirror image
    assert np.allclose(handshape("point", "right"), handshape("point", "left") * [1, -1, -1])


def test_synth_cli(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "out"), "--n", "2", "--seed", "1", "--json"]) == 0
    out = capsys.readouterr().out
    assert '"seed": 1' in out and (tmp_path / "out" / "seq_001.npz").is_file()
    assert main(["synth", str(tmp_path / "bad"), "--n", "0"]) == 2
    assert not (tmp_path / "bad").exists()
    (tmp_path / "file").write_text("x")
    assert main(["synth", str(tmp_path / "file"), "--n", "1"]) == 2


def test_shoulder_sign_holds_the_palm_at_the_opposite_shoulder_without_penetrating():
    """SHOULDER's palm is at the left shoulder during the hold (its nearest landmark by far),
    and the arm reaching across does not go through the chest (the elbow is lifted)."""
    from embody.body.landmarks import BODY_LANDMARKS
    from embody.collision.depth import motion_depths
    from embody.metrics.embodiments import human_track
    from embody.synth import generate_sequence
    from embody.synth.lexicon import LEXICON

    body = load_body_model()
    sign = next(s for s in LEXICON if s.gloss == "SHOULDER")
    for seed, index in ((1, 1000 + LEXICON.index(sign)), (0, 5000), (1, 5001)):
        m = generate_sequence(seed, index, signs=[sign])
        track = human_track(m, body, with_contacts=False)
        s = m.meta["signs"][0]
        hold = slice(s["start"] + (s["end"] - s["start"]) // 3, s["end"] - (s["end"] - s["start"]) // 3)
        names = list(track.names)
        palm = track.points[hold, names.index("right_palm")]
        lms = np.stack([track.points[hold, names.index(n)] for n in BODY_LANDMARKS], 1)
        dist = np.linalg.norm(lms - palm[:, None], axis=-1)
        shoulder = dist[:, BODY_LANDMARKS.index("left_shoulder")]
        assert np.all(dist.argmin(1) == BODY_LANDMARKS.index("left_shoulder")), (seed, index)
        assert shoulder.mean() < 0.06, (seed, index, shoulder.mean())
        others = np.delete(dist, BODY_LANDMARKS.index("left_shoulder"), axis=1).min(1)
        assert np.all(others - shoulder > 0.05)  # not a face sign in disguise
        # the palm lies on the shoulder: no other hand point is nearer (the thumb does not touch)
        for point in ("thumb_tip", "index_tip", "middle_tip"):
            tip = track.points[hold, names.index(f"right_{point}")] - lms[:, BODY_LANDMARKS.index("left_shoulder")]
            assert np.all(np.linalg.norm(tip, axis=-1) > shoulder + 0.03), (seed, index, point)
        assert motion_depths(body, m.pose, m.betas).max() < 0.003, (seed, index)


def test_default_dataset_from_another_generator_is_regenerated(tmp_path):
    """A folder left by an older generator (e.g. before the SHOULDER sign moved to the shoulder)
    is replaced, not silently reused; a current one is reused."""
    from embody.io import save

    root = default_dataset(tmp_path, n=2, seed=3)
    fresh = load(root / "seq_001.npz")
    old = load(root / "seq_000.npz")
    old.meta["generator"] = "embody-synth-0"
    old.pose[:] = 0.0  # the old generator's (different) motion
    save(old, root / "seq_000.npz")
    assert default_dataset(tmp_path, n=2, seed=3) == root
    again = load(root / "seq_000.npz")
    assert again.meta["generator"] == GENERATOR_VERSION
    assert np.abs(again.pose).max() > 0.1
    np.testing.assert_array_equal(load(root / "seq_001.npz").pose, fresh.pose)
    assert [p.name for p in tmp_path.iterdir()] == [root.name]  # nothing stale or temporary left
    stamp = (root / "seq_000.npz").stat().st_mtime_ns
    assert default_dataset(tmp_path, n=2, seed=3) == root
    assert (root / "seq_000.npz").stat().st_mtime_ns == stamp
