"""Frame rate, up axis and hand convention per format, where each came from, the overrides, and
per-frame sequence folders (.pkl and .npz) read in numeric frame order."""

from __future__ import annotations

import gzip
import json
import pickle

import numpy as np
import pytest

from embody.cli import main
from embody.config import load_config
from embody.errors import InputError
from embody.io import hand_mean, load, load_dataset, save
from embody.tasks.execute import source_key
from embody.tasks.pipeline import Context
from embody.tasks.stages import SOURCE

RNG = np.random.default_rng(3)
T = 5


def _frame(i: int) -> dict[str, np.ndarray]:
    """A SOKE-keyed frame whose body pose encodes its index (to check frame order)."""
    return {"smplx_root_pose": np.zeros(3), "smplx_body_pose": np.full(63, 0.01 * i),
            "smplx_lhand_pose": np.zeros(45), "smplx_rhand_pose": np.zeros(45),
            "smplx_jaw_pose": np.zeros(3), "smplx_shape": np.zeros(10), "smplx_expr": np.zeros(10),
            "cam_trans": np.array([0.0, 0.0, 2.0])}


def _frames_dir(d, names, suffix=".pkl"):
    d.mkdir(parents=True)
    for i, name in names:
        rec = _frame(i)
        if suffix == ".pkl":
            (d / f"{name}.pkl").write_bytes(pickle.dumps(rec))
        else:
            np.savez(d / f"{name}.npz", **rec)
    return d


def _order(motion) -> list[int]:
    return [int(round(v / 0.01)) for v in motion.pose[:, 1, 0]]


def _origin(motion, name: str) -> str:
    return motion.source.provenance[name]["origin"]


# --- frame rate, up axis, hands: from the data, detected, or a documented default ----------

def test_amass_fps_from_data_z_up_absolute(tmp_path):
    np.savez(tmp_path / "a.npz", poses=np.zeros((T, 165)), trans=np.zeros((T, 3)),
             mocap_frame_rate=np.array(120.0))
    m = load(tmp_path / "a.npz")
    assert m.fps == 120.0 and _origin(m, "fps") == "data: mocap_frame_rate"
    assert m.source.provenance["up_axis"]["value"] == "z" and _origin(m, "up_axis").startswith("default")
    assert m.source.hand_convention == "absolute"


def test_beat2_is_detected_y_up_with_relative_hands(tmp_path):
    trans = np.tile([0.1, 0.9, 0.2], (T, 1))
    np.savez(tmp_path / "b.npz", poses=np.zeros((T, 165)), trans=trans, betas=np.zeros(300),
             model=np.array("smplx2020"), gender=np.array("neutral"),
             mocap_frame_rate=np.array(30))
    m = load(tmp_path / "b.npz")
    assert m.source.format == "beat2" and m.fps == 30.0
    assert m.source.provenance["up_axis"]["value"] == "y"
    assert _origin(m, "up_axis").startswith("detected: BEAT2")
    assert np.allclose(m.transl, trans, atol=1e-6)  # y-up already: not rotated
    assert np.allclose(m.pose[:, 0], 0.0, atol=1e-6)
    assert m.source.hand_convention == "relative"  # zero relative hands = the hand mean
    assert np.allclose(m.pose[0, 25:55], hand_mean(), atol=1e-6)
    # overrides: treat it as z-up with absolute hands
    z = load(tmp_path / "b.npz", up_axis="z", hands="absolute")
    assert np.allclose(z.transl[0], [0.1, 0.2, -0.9], atol=1e-6)  # z-up → y-up: (x, z, -y)
    assert np.allclose(z.pose[0, 25:55], 0.0) and _origin(z, "hands").startswith("override")


def test_signavatars_default_24_fps_or_its_own(tmp_path):
    raw = np.zeros((T, 182))
    (tmp_path / "s.pkl").write_bytes(pickle.dumps({"smplx": raw}))
    m = load(tmp_path / "s.pkl")
    assert m.fps == 24.0 and "SignAvatars" in _origin(m, "fps") and _origin(m, "fps").startswith("default")
    (tmp_path / "t.pkl").write_bytes(pickle.dumps({"smplx": raw, "fps": 25}))
    assert load(tmp_path / "t.pkl").fps == 25.0


@pytest.mark.parametrize("names, fps, where", [
    ([(i, f"{i:06d}") for i in range(T)], 30.0, "CSL-Daily"),
    ([(i, f"vid-1_{i}_3D") for i in range(T)], 24.0, "How2Sign"),
    ([(i, f"images{i:04d}") for i in range(T)], 25.0, "Phoenix"),
])
@pytest.mark.parametrize("suffix", [".pkl", ".npz"])
def test_per_frame_folder_fps_by_dataset(tmp_path, names, fps, where, suffix):
    m = load(_frames_dir(tmp_path / "seq", names, suffix))
    assert m.fps == fps and where in _origin(m, "fps")
    assert m.source.hand_convention == "relative" and m.source.provenance["up_axis"]["value"] == "camera"
    assert m.source.format == ("frames-npz" if suffix == ".npz" else "soke")


def test_plain_arrays_and_embody_files(tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((T, 165)))
    m = load(tmp_path / "p.npy")
    assert m.fps == 30.0 and _origin(m, "fps").startswith("default")
    np.savez(tmp_path / "q.npz", poses=np.zeros((T, 165)), fps=np.array(50.0))
    assert _origin(load(tmp_path / "q.npz"), "fps") == "data: fps"
    again = load(save(load(tmp_path / "p.npy", fps=24), tmp_path / "e.npz"))
    assert again.fps == 24.0 and again.source.format == "embody"
    assert _origin(again, "fps") == "data: mocap_frame_rate"


# --- overrides ----------------------------------------------------------------------------

def test_fps_override_wins_and_says_so(tmp_path):
    np.savez(tmp_path / "a.npz", poses=np.zeros((T, 165)), mocap_frame_rate=np.array(120.0))
    m = load(tmp_path / "a.npz", fps=30)
    assert m.fps == 30.0 and _origin(m, "fps").startswith("override") and "120" in _origin(m, "fps")
    with pytest.raises(InputError, match="fps"):
        load(tmp_path / "a.npz", fps=-1)
    with pytest.raises(InputError, match="up_axis"):
        load(tmp_path / "a.npz", up_axis="x")


def test_config_io_overrides_the_dataset_and_enters_the_source_key(tmp_path):
    _frames_dir(tmp_path / "ds" / "seq1", [(i, f"{i}") for i in range(T)])
    (tmp_path / "ds" / "s.pkl").write_bytes(pickle.dumps({"smplx": np.zeros((T, 182))}))
    (tmp_path / "ds.csv").write_text("path,text\nds/seq1,hello\nds/s.pkl,hi\n")
    folder, single = load_dataset(tmp_path / "ds.csv")
    plain, at25 = load_config(), load_config(sets=["io.fps=25"])
    for ref, default in ((folder, 30.0), (single, 24.0)):
        assert SOURCE.compute(Context(plain, str(tmp_path), "r"), {"ref": ref}).fps == default
        assert SOURCE.compute(Context(at25, str(tmp_path), "r"), {"ref": ref}).fps == 25.0
    keys = {source_key(SOURCE, Context(cfg, str(tmp_path), "r"), single)
            for cfg in (plain, at25, load_config(sets=["io.fps=24"]),
                        load_config(sets=["io.up_axis=y"]), load_config(sets=["io.hands=absolute"]))}
    assert len(keys) == 5  # fps, up axis and hands each change the source step's key
    assert source_key(SOURCE, Context(load_config(sets=["io.fps=25"]), str(tmp_path), "r"),
                      single) in keys  # and the same override gives the same key


def test_inspect_prints_where_fps_up_axis_and_hands_came_from(tmp_path, capsys):
    raw = np.zeros((T, 182))
    (tmp_path / "s.pkl").write_bytes(pickle.dumps({"smplx": raw}))
    assert main(["inspect", str(tmp_path / "s.pkl")]) == 0
    out = capsys.readouterr().out
    assert "fps from         24: default: SignAvatars is 24 fps (its README)" in out
    assert "up axis          camera: default" in out and "hands from       relative: default" in out
    assert main(["inspect", str(tmp_path / "s.pkl"), "--fps", "30", "--hands", "absolute",
                 "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["fps"] == 30.0 and info["provenance"]["fps"]["origin"].startswith("override")
    assert info["hand_convention"] == "absolute"
    assert main(["inspect", str(tmp_path / "s.pkl"), "--set", "io.fps=25", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fps"] == 25.0
    assert main(["inspect", str(tmp_path / "s.pkl"), "--up-axis", "w"]) == 2


# --- per-frame folders ---------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".pkl", ".npz"])
def test_frames_are_read_in_numeric_order(tmp_path, suffix):
    # not zero-padded: lexical order would be 0, 1, 10, 11, 2, ...
    names = [(i, f"clipA_{i}_3D") for i in (3, 11, 0, 2, 10, 1, 9)]
    m = load(_frames_dir(tmp_path / "clipA", names, suffix))
    assert _order(m) == [0, 1, 2, 3, 9, 10, 11]
    names = [(i, f"{i}") for i in (12, 7, 100, 8)]
    assert _order(load(_frames_dir(tmp_path / "plain", names, suffix))) == [7, 8, 12, 100]


def test_npz_frame_folders_from_a_manifest_and_a_soke_split(tmp_path):
    root = tmp_path / "soke"
    for name in ("a", "b"):
        _frames_dir(root / "poses" / name, [(i, f"{i}") for i in range(T)], ".npz")
    entries = [{"name": "a", "text": "first"}, {"name": "b", "text": "second"}]
    (root / "csl_clean.test").write_bytes(gzip.compress(pickle.dumps(entries)))
    ds = load_dataset(root, "test")
    motions = [ref.load() for ref in ds]
    assert [m.meta["text"] for m in motions] == ["first", "second"]
    assert all(m.source.format == "frames-npz" and m.num_frames == T for m in motions)
    (tmp_path / "list.csv").write_text("path,text\nsoke/poses/b,second\n")
    m = load_dataset(tmp_path / "list.csv")[0].load(fps=25)
    assert m.num_frames == T and m.fps == 25.0 and m.meta["text"] == "second"
    assert _order(m) == list(range(T))


def test_folder_of_motion_npz_files_is_still_a_dataset(tmp_path, capsys):
    for name in ("x", "y"):
        np.savez(tmp_path / f"{name}.npz", poses=np.zeros((T, 165)), mocap_frame_rate=np.array(60.0))
    assert main(["inspect", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sequences"] == 2
    with pytest.raises(InputError, match="not a sequence folder"):
        load(tmp_path)


def test_mixed_and_single_frames_are_refused(tmp_path):
    d = _frames_dir(tmp_path / "mix", [(0, "0"), (1, "1")])
    np.savez(d / "2.npz", **_frame(2))
    with pytest.raises(InputError, match="mixes"):
        load(d)
    with pytest.raises(InputError, match="single per-frame file"):
        load(d / "2.npz")
