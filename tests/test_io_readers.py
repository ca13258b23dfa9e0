"""Readers of the field's formats: layouts, hand conventions and frame conversions."""

from __future__ import annotations

import gzip
import pickle

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embody.io import absolute_to_relative, hand_mean, load, relative_to_absolute, save

RNG = np.random.default_rng(7)
T = 6


def _amass(path, poses, **extra):
    data = {"poses": poses, "trans": RNG.normal(size=(len(poses), 3)), "betas": RNG.normal(size=16),
            "gender": np.array("female"), "mocap_frame_rate": np.array(120.0)}
    data.update(extra)
    np.savez(path, **{k: v for k, v in data.items() if v is not None})
    return data


def test_hand_mean_matches_mannequin_asset_and_round_trips():
    mean = hand_mean()
    assert mean.shape == (30, 3)
    assert np.allclose(mean[0], [0.11167871, 0.04289218, -0.41644183], atol=1e-6)
    pose = RNG.normal(size=(T, 55, 3)).astype(np.float32)
    absolute = relative_to_absolute(pose)
    assert np.allclose(absolute[:, 25:55] - pose[:, 25:55], mean, atol=1e-6)
    assert np.array_equal(absolute[:, :25], pose[:, :25])
    assert np.allclose(absolute_to_relative(absolute), pose, atol=1e-6)


def test_amass_smplx_z_up_becomes_y_up(tmp_path):
    poses = RNG.normal(scale=0.3, size=(T, 165))
    data = _amass(tmp_path / "a.npz", poses)
    m = load(tmp_path / "a.npz")
    assert m.source.format == "amass-smplx" and m.source.hand_convention == "absolute"
    assert m.fps == 120.0 and m.gender == "female" and m.betas.shape == (10,)
    assert np.allclose(m.betas, data["betas"][:10], atol=1e-6)
    # Every non-root joint is parent-relative: unchanged.
    assert np.allclose(m.pose[:, 1:], poses.reshape(T, 55, 3)[:, 1:], atol=1e-6)
    # A point fixed to the pelvis frame lands where the z-up world point lands after -90° about x.
    fix = Rotation.from_euler("x", -90, degrees=True)
    p = np.array([0.1, 0.2, 0.3])
    world_z = Rotation.from_rotvec(poses[:, :3]).apply(p) + data["trans"]
    world_y = Rotation.from_rotvec(m.pose[:, 0].astype(np.float64)).apply(p) + m.transl
    assert np.allclose(world_y, fix.apply(world_z), atol=1e-5)


def test_amass_known_point(tmp_path):
    poses = np.zeros((T, 165))
    _amass(tmp_path / "a.npz", poses, trans=np.tile([0.0, 0.0, 1.5], (T, 1)))
    m = load(tmp_path / "a.npz")
    assert np.allclose(m.transl, [0.0, 1.5, 0.0], atol=1e-6)  # z-up height → y-up height
    # the world's up (+z in AMASS) becomes +y
    assert np.allclose(Rotation.from_rotvec(m.pose[0, 0]).apply([0, 0, 1]), [0, 1, 0], atol=1e-6)


def test_amass_old_framerate_key(tmp_path):
    _amass(tmp_path / "old.npz", np.zeros((T, 165)), mocap_frame_rate=None,
           mocap_framerate=np.array(60.0))
    assert load(tmp_path / "old.npz").fps == 60.0


def test_smplh_index_mapping(tmp_path):
    poses = RNG.normal(scale=0.3, size=(T, 156))
    _amass(tmp_path / "h.npz", poses)
    m = load(tmp_path / "h.npz")
    assert m.source.format == "amass-smplh"
    pose = m.pose.reshape(T, 165)
    assert np.allclose(pose[:, 3:66], poses[:, 3:66], atol=1e-6)
    assert np.allclose(pose[:, 75:120], poses[:, 66:111], atol=1e-6)   # left hand
    assert np.allclose(pose[:, 120:165], poses[:, 111:156], atol=1e-6)  # right hand
    assert np.all(pose[:, 66:75] == 0)                                  # jaw and eyes


def _soke_root(tmp_path, names=("seqA", "seqB"), frames=4):
    root = tmp_path / "soke"
    frames_by_name = {}
    for name in names:
        d = root / "poses" / name
        d.mkdir(parents=True)
        recs = []
        for i in range(frames):
            rec = {"smplx_root_pose": RNG.normal(size=3) * 0.2, "smplx_body_pose": RNG.normal(size=63) * 0.2,
                   "smplx_lhand_pose": RNG.normal(size=45) * 0.2, "smplx_rhand_pose": RNG.normal(size=45) * 0.2,
                   "smplx_jaw_pose": RNG.normal(size=3) * 0.1, "smplx_shape": np.full(10, 0.5),
                   "smplx_expr": np.zeros(10), "cam_trans": np.array([0.0, -1.0, 3.0])}
            (d / f"{i:06d}.pkl").write_bytes(pickle.dumps(rec))
            recs.append(rec)
        frames_by_name[name] = recs
    for split, split_names in (("train", names[:1]), ("val", names[1:]), ("test", ())):
        entries = [{"name": n, "text": f"text of {n}", "gloss": "A/B"} for n in split_names]
        (root / f"csl_clean.{split}").write_bytes(gzip.compress(pickle.dumps(entries)))
    return root, frames_by_name


def test_soke_sequence_folder(tmp_path):
    root, recs = _soke_root(tmp_path)
    m = load(root / "poses" / "seqA")
    assert m.source.format == "soke" and m.source.hand_convention == "relative"
    assert m.num_frames == 4 and m.fps == 30.0
    rec = recs["seqA"][2]
    # hands relative → absolute: add the mean
    assert np.allclose(m.pose[2, 25:40], rec["smplx_lhand_pose"].reshape(15, 3) + hand_mean()[:15], atol=1e-5)
    assert np.allclose(m.pose[2, 40:55], rec["smplx_rhand_pose"].reshape(15, 3) + hand_mean()[15:], atol=1e-5)
    assert np.allclose(m.pose[2, 22], rec["smplx_jaw_pose"], atol=1e-6)
    assert np.allclose(m.pose[2, 1:22].reshape(-1), rec["smplx_body_pose"], atol=1e-6)
    # camera → y-up: 180° about x
    assert np.allclose(m.transl[2], [0.0, 1.0, -3.0], atol=1e-6)
    flip = Rotation.from_euler("x", 180, degrees=True)
    expect = (flip * Rotation.from_rotvec(rec["smplx_root_pose"])).as_matrix()
    assert np.allclose(Rotation.from_rotvec(m.pose[2, 0]).as_matrix(), expect, atol=1e-5)
    assert np.allclose(m.betas, 0.5)


def test_signavatars_layout(tmp_path):
    raw = RNG.normal(scale=0.2, size=(T, 182))
    raw[:, 179:182] = [0.1, -0.2, 2.0]
    (tmp_path / "s.pkl").write_bytes(pickle.dumps({"smplx": raw}))
    m = load(tmp_path / "s.pkl")
    assert m.source.format == "signavatars" and m.source.hand_convention == "relative"
    pose = m.pose.reshape(T, 165)
    assert np.allclose(pose[:, 3:66], raw[:, 3:66], atol=1e-6)
    assert np.allclose(pose[:, 75:120], raw[:, 66:111] + hand_mean()[:15].reshape(-1), atol=1e-5)
    assert np.allclose(pose[:, 120:165], raw[:, 111:156] + hand_mean()[15:].reshape(-1), atol=1e-5)
    assert np.allclose(pose[:, 66:69], raw[:, 156:159], atol=1e-6)
    assert np.allclose(m.betas, raw[:, 159:169].mean(0), atol=1e-6)
    assert np.allclose(m.transl, [0.1, 0.2, -2.0], atol=1e-6)


@pytest.mark.parametrize("layout", ["npy165", "npy55", "npz_single", "npz_poses"])
def test_plain_arrays(tmp_path, layout):
    poses = RNG.normal(scale=0.3, size=(T, 165)).astype(np.float32)
    if layout == "npy165":
        path = tmp_path / "p.npy"
        np.save(path, poses)
    elif layout == "npy55":
        path = tmp_path / "p.npy"
        np.save(path, poses.reshape(T, 55, 3))
    elif layout == "npz_single":
        path = tmp_path / "p.npz"
        np.savez(path, motion=poses)
    else:
        path = tmp_path / "p.npz"
        np.savez(path, poses=poses, fps=np.array(25.0))
    m = load(path)
    assert m.source.format == "array" and m.source.hand_convention == "absolute"
    assert np.array_equal(m.pose165(), poses)  # y-up, absolute: untouched
    assert m.fps == (25.0 if layout == "npz_poses" else 30.0)
    assert np.all(m.transl == 0) and np.all(m.betas == 0)


def test_soke_model_features(tmp_path):
    feats = RNG.normal(scale=0.2, size=(T, 133)).astype(np.float32)
    np.save(tmp_path / "gen.npy", feats)
    m = load(tmp_path / "gen.npy")
    assert m.source.format == "soke-features" and m.source.hand_convention == "relative"
    pose = m.pose165()
    assert np.all(pose[:, :36] == 0)                                     # root + joints 1-11
    assert np.allclose(pose[:, 36:66], feats[:, 0:30])                   # neck ... wrists
    assert np.allclose(pose[:, 75:120], feats[:, 30:75] + hand_mean()[:15].reshape(-1), atol=1e-6)
    assert np.allclose(pose[:, 120:165], feats[:, 75:120] + hand_mean()[15:].reshape(-1), atol=1e-6)
    assert np.allclose(pose[:, 66:69], feats[:, 120:123]) and np.all(pose[:, 69:75] == 0)


def test_save_round_trip_does_not_rotate_again(tmp_path):
    poses = RNG.normal(scale=0.3, size=(T, 165))
    _amass(tmp_path / "a.npz", poses)
    m = load(tmp_path / "a.npz")
    m.meta.update({"text": "你好", "artifacts": [{"kind": "jitter", "start": 1, "end": 3}]})
    save(m, tmp_path / "out" / "b.npz")
    back = load(tmp_path / "out" / "b.npz")
    m2 = load(tmp_path / "a.npz")
    m2.meta["score"] = np.float32(0.5)
    m2.meta["curve"] = np.arange(3)
    save(m2, tmp_path / "np.npz")
    assert load(tmp_path / "np.npz").meta == {"score": 0.5, "curve": [0, 1, 2]}
    assert back.source.format == "embody" and back.source.hand_convention == "absolute"
    assert np.array_equal(back.pose, m.pose) and np.array_equal(back.transl, m.transl)
    assert np.array_equal(back.betas, m.betas)
    assert back.fps == m.fps and back.gender == m.gender and back.meta == m.meta
    # a plain AMASS reader sees the usual keys
    with np.load(tmp_path / "out" / "b.npz") as z:
        assert z["poses"].shape == (T, 165) and float(z["mocap_frame_rate"]) == 120.0
    # same motion, same bytes
    save(m, tmp_path / "c.npz")
    assert (tmp_path / "c.npz").read_bytes() == (tmp_path / "out" / "b.npz").read_bytes()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["b.npz"]  # no temp leftovers
