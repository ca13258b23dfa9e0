"""Bad inputs: one-line errors naming file and field, exit 2 from the CLI, nothing written."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from embody.cli import main
from embody.errors import InputError
from embody.io import load, load_dataset, save


def _good_amass(path, t=5):
    np.savez(path, poses=np.zeros((t, 165)), trans=np.zeros((t, 3)), betas=np.zeros(16),
             gender=np.array("neutral"), mocap_frame_rate=np.array(30.0))


def _truncated(d):
    _good_amass(d / "t.npz")
    raw = (d / "t.npz").read_bytes()
    (d / "t.npz").write_bytes(raw[: len(raw) // 2])
    return d / "t.npz", None


def _wrong_shape(d):
    np.savez(d / "w.npz", poses=np.zeros((5, 160)), mocap_frame_rate=np.array(30.0))
    return d / "w.npz", "poses"


def _nan(d):
    poses = np.zeros((5, 165))
    poses[2, 7] = np.nan
    np.savez(d / "n.npz", poses=poses, mocap_frame_rate=np.array(30.0))
    return d / "n.npz", "poses"


def _nan_trans(d):
    np.savez(d / "nt.npz", poses=np.zeros((5, 165)), trans=np.full((5, 3), np.inf),
             mocap_frame_rate=np.array(30.0))
    return d / "nt.npz", "trans"


def _empty_dir(d):
    (d / "empty").mkdir()
    return d / "empty", None


def _unknown(d):
    (d / "m.txt").write_text("hello")
    return d / "m.txt", None


def _bad_pickle(d):
    (d / "b.pkl").write_bytes(b"\x80\x04not a pickle at all")
    return d / "b.pkl", None


def _hostile_pickle(d):
    import os
    (d / "h.pkl").write_bytes(pickle.dumps(os.getcwd))  # a callable: refused, never imported
    return d / "h.pkl", None


def _signavatars_width(d):
    (d / "s.pkl").write_bytes(pickle.dumps({"smplx": np.zeros((5, 180))}))
    return d / "s.pkl", "smplx"


def _soke_missing_key(d):
    seq = d / "seq"
    seq.mkdir()
    rec = {"smplx_root_pose": np.zeros(3), "smplx_body_pose": np.zeros(63), "smplx_lhand_pose": np.zeros(45),
           "smplx_rhand_pose": np.zeros(45)}
    for i in range(3):
        (seq / f"{i:03d}.pkl").write_bytes(pickle.dumps(rec))
    return seq, "smplx_jaw_pose"


def _one_frame(d):
    np.save(d / "one.npy", np.zeros((1, 165)))
    return d / "one.npy", "pose"


def _bad_fps(d):
    np.savez(d / "f.npz", poses=np.zeros((5, 165)), mocap_frame_rate=np.array(-1.0))
    return d / "f.npz", "mocap_frame_rate"


CASES = [_truncated, _wrong_shape, _nan, _nan_trans, _empty_dir, _unknown, _bad_pickle,
         _hostile_pickle, _signavatars_width, _soke_missing_key, _one_frame, _bad_fps]


@pytest.mark.parametrize("make", CASES, ids=[c.__name__.strip("_") for c in CASES])
def test_load_raises_input_error_naming_file_and_field(tmp_path, make):
    path, field = make(tmp_path)
    with pytest.raises(InputError) as err:
        load(path)
    assert err.value.field == field
    assert path.name in err.value.path
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("make", [_truncated, _nan, _empty_dir, _unknown, _bad_pickle],
                         ids=["truncated", "nan", "empty_dir", "unknown", "bad_pickle"])
def test_inspect_bad_file_exits_2_with_one_line(tmp_path, capsys, make):
    path, field = make(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and path.name in err
    if field:
        assert f"'{field}'" in err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written


def test_save_refuses_unserialisable_meta_and_writes_nothing(tmp_path):
    _good_amass(tmp_path / "a.npz")
    m = load(tmp_path / "a.npz")
    m.meta["bad"] = object()
    with pytest.raises(InputError) as err:
        save(m, tmp_path / "out.npz")
    assert err.value.field == "meta"
    assert not (tmp_path / "out.npz").exists()


def test_bad_file_in_dataset_fails_only_its_own_load(tmp_path):
    _good_amass(tmp_path / "a.npz")
    _truncated(tmp_path)
    ds = load_dataset(tmp_path)
    assert ds.ids == ["a", "t"]
    assert ds[0].load().num_frames == 5
    with pytest.raises(InputError):
        ds[1].load()
