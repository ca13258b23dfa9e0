"""Datasets: folders, SOKE roots with splits, CSV manifests; lazy and with stable ids."""

from __future__ import annotations

import gzip
import pickle

import numpy as np
import pytest

from embody.config.io import IOConfig
from embody.errors import InputError
from embody.io import SequenceRef, load_dataset


def _npz(path, t=4):
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, poses=np.zeros((t, 165)), mocap_frame_rate=np.array(30.0))


def _soke(root, names=("b_seq", "a_seq")):
    rec = {"smplx_root_pose": np.zeros(3), "smplx_body_pose": np.zeros(63), "smplx_lhand_pose": np.zeros(45),
           "smplx_rhand_pose": np.zeros(45), "smplx_jaw_pose": np.zeros(3), "smplx_shape": np.zeros(10),
           "smplx_expr": np.zeros(10), "cam_trans": np.zeros(3)}
    for name in names:
        (root / "poses" / name).mkdir(parents=True)
        for i in range(3):
            (root / "poses" / name / f"{i:06d}.pkl").write_bytes(pickle.dumps(rec))
    split = [{"name": n, "text": f"文本 {n}"} for n in names]
    (root / "csl_clean.train").write_bytes(gzip.compress(pickle.dumps(split)))
    (root / "csl_clean.val").write_bytes(gzip.compress(pickle.dumps(split[:1])))


def test_folder_is_recursive_sorted_with_stable_ids(tmp_path):
    for rel in ("z.npz", "sub/b.npz", "sub/a.npz", "a.npz"):
        _npz(tmp_path / rel)
    (tmp_path / "notes.txt").write_text("ignored")
    ds = load_dataset(tmp_path)
    assert len(ds) == 4
    assert ds.ids == ["a", "sub/a", "sub/b", "z"]
    assert load_dataset(tmp_path).ids == ds.ids  # stable across listings
    ref = ds.get("sub/b")
    assert isinstance(ref, SequenceRef) and ref.text is None and ref.source_files == (tmp_path / "sub/b.npz",)
    m = ref.load()
    assert m.meta["id"] == "sub/b" and "text" not in m.meta


def test_soke_split_attaches_text(tmp_path):
    _soke(tmp_path)
    train = load_dataset(tmp_path, split="train")
    assert train.ids == ["b_seq", "a_seq"]  # split order
    assert [r.text for r in train] == ["文本 b_seq", "文本 a_seq"]
    m = train[1].load()
    assert m.meta["text"] == "文本 a_seq" and m.num_frames == 3 and m.source.format == "soke"
    assert len(load_dataset(tmp_path, split="val")) == 1
    assert load_dataset(tmp_path).ids == ["a_seq", "b_seq"]  # no split: every folder, sorted
    for split_file in tmp_path.glob("csl_clean.*"):
        split_file.unlink()
    assert load_dataset(tmp_path).ids == ["a_seq", "b_seq"]  # a SOKE root even without index files
    with pytest.raises(InputError) as err:
        load_dataset(tmp_path, split="test")
    assert "csl_clean.test" in str(err.value)
    with pytest.raises(InputError) as err:
        load_dataset(tmp_path, split="dev")
    assert err.value.field == "split"


def test_soke_split_name_missing_folder_fails_at_load_only(tmp_path):
    _soke(tmp_path)
    entries = [{"name": "missing", "text": "x"}, {"name": "a_seq", "text": "y"}]
    (tmp_path / "csl_clean.val").write_bytes(gzip.compress(pickle.dumps(entries)))
    ds = load_dataset(tmp_path, split="val")
    assert len(ds) == 2 and ds[1].load().num_frames == 3
    with pytest.raises(InputError):
        ds[0].load()


def test_csv_manifest_resolves_relative_paths(tmp_path):
    _npz(tmp_path / "data" / "one.npz")
    _npz(tmp_path / "data" / "two.npz", t=6)
    (tmp_path / "lists").mkdir()
    (tmp_path / "lists" / "m.csv").write_text('path,text\n../data/two.npz,"hello, world"\n../data/one.npz,\n')
    with pytest.raises(InputError, match="line 2: '../data/two.npz' is outside"):
        load_dataset(tmp_path / "lists" / "m.csv")  # refused unless the config allows it
    ds = load_dataset(tmp_path / "lists" / "m.csv", limits=IOConfig(allow_outside_paths=True))
    assert ds.ids == ["../data/two", "../data/one"]
    assert ds[0].path == tmp_path / "lists" / "../data/two.npz"
    m = ds[0].load()
    assert m.num_frames == 6 and m.meta["text"] == "hello, world"
    assert ds[1].text is None


@pytest.mark.parametrize("content,field", [("file,text\nx.npz,a\n", "path"), ("path,text\n,a\n", "path"),
                                           ("path,text\na.npz,x\na.npy,y\n", "id")])
def test_bad_manifest(tmp_path, content, field):
    (tmp_path / "m.csv").write_text(content)
    with pytest.raises(InputError) as err:
        load_dataset(tmp_path / "m.csv")
    assert err.value.field == field


def test_empty_or_missing_dataset(tmp_path):
    with pytest.raises(InputError):
        load_dataset(tmp_path)
    with pytest.raises(InputError):
        load_dataset(tmp_path / "nope")
