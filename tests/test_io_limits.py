"""Input bounds and malformed metadata: one clear error naming file and field, exit 2.

Sizes are refused from headers, before decompression; fps, poses and translations are bounded;
bool/complex values, bad `embody_meta`, non-UTF-8 configs and corrupt run manifests are errors.
"""

from __future__ import annotations

import gzip
import io
import json
import pickle
import tracemalloc
import zipfile

import numpy as np
import pytest

from embody.cli import main
from embody.config.io import IOConfig
from embody.csvsafe import csv_safe
from embody.errors import InputError
from embody.io import load, load_dataset
from embody.io.dataset import SequenceRef


def _amass(path, t=5, **over):
    arrays = dict(poses=np.zeros((t, 165)), trans=np.zeros((t, 3)), betas=np.zeros(16),
                  gender=np.array("neutral"), mocap_frame_rate=np.array(30.0))
    arrays.update(over)
    np.savez(path, **arrays)
    return path


def _zeros_npz(path, frames, width=165):
    """An npz whose `poses` is `frames` × `width` float32 zeros, written without allocating it."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False,
                                                  "shape": (frames, width)})
    block = bytes(4 * width * 1000)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("poses.npy", "w", force_zip64=True) as fh:
            fh.write(header.getvalue())
            for _ in range(frames // 1000):
                fh.write(block)
        zf.writestr("mocap_frame_rate.npy", _npy(np.array(30.0)))
    return path


def _npy(arr) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr)
    return buf.getvalue()


def test_long_npz_is_refused_from_its_header_without_decompressing(tmp_path):
    path = _zeros_npz(tmp_path / "long.npz", 120_000)  # 79 MB of zeros in ~80 kB
    assert path.stat().st_size < 1_000_000
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="120000 frames exceeds io.max_frames=50000") as err:
            load(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert err.value.field == "poses"
    assert peak < 10e6  # the 79 MB array was never allocated
    assert load(path, limits=IOConfig(max_frames=200_000)).num_frames == 120_000


def test_npy_and_soke_folder_frame_limits(tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((12, 165)))
    with pytest.raises(InputError, match="io.max_frames=10"):
        load(tmp_path / "p.npy", limits=IOConfig(max_frames=10))
    seq = tmp_path / "seq"
    seq.mkdir()
    frame = {k: np.zeros(n) for k, n in (("smplx_root_pose", 3), ("smplx_body_pose", 63),
                                         ("smplx_lhand_pose", 45), ("smplx_rhand_pose", 45),
                                         ("smplx_jaw_pose", 3))}
    for i in range(4):
        (seq / f"{i:03d}.pkl").write_bytes(pickle.dumps(frame))
    with pytest.raises(InputError, match="4 frames exceeds io.max_frames=3") as err:
        load(seq, limits=IOConfig(max_frames=3))
    assert err.value.field == "frames"
    assert load(seq).num_frames == 4


@pytest.mark.parametrize("fps", [1e-9, 0.002, 1e9])
def test_absurd_frame_rates_are_refused(tmp_path, capsys, fps):
    path = _amass(tmp_path / "f.npz", mocap_frame_rate=np.array(fps))
    with pytest.raises(InputError, match="outside io.min_fps..io.max_fps") as err:
        load(path)
    assert err.value.field == "fps"
    assert main(["inspect", str(_amass(tmp_path / "ok.npz")), "--set", "io.max_fps=20"]) == 2
    assert "io.min_fps..io.max_fps (1..20)" in capsys.readouterr().err
    np.save(tmp_path / "a.npy", np.zeros((5, 165)))
    assert main(["inspect", str(tmp_path / "a.npy"), "--fps", "1e9"]) == 2
    err = capsys.readouterr().err.strip()
    # `--fps` is validated as config (`io.fps`) before the file is read: one line, exit 2
    assert len(err.splitlines()) == 1 and "io.fps" in err


def test_pose_and_translation_bounds(tmp_path):
    poses = np.zeros((5, 165))
    poses[3, 3 * 20 + 1] = 40.0  # |axis-angle| 40 rad > 10π at joint 20
    with pytest.raises(InputError, match="frame 3, joint 20 exceeds io.max_axis_angle") as err:
        load(_amass(tmp_path / "p.npz", poses=poses))
    assert err.value.field == "pose"
    poses[3, 3 * 20 + 1] = 3 * np.pi  # large but sane: accepted
    assert load(_amass(tmp_path / "ok.npz", poses=poses)).num_frames == 5
    with pytest.raises(InputError, match="exceeds io.max_translation") as err:
        load(_amass(tmp_path / "t.npz", trans=np.full((5, 3), 1e7)))
    assert err.value.field == "transl"


@pytest.mark.parametrize("dtype", [bool, complex])
def test_bool_and_complex_arrays_are_refused(tmp_path, dtype):
    with pytest.raises(InputError, match="values are refused") as err:
        load(_amass(tmp_path / "b.npz", poses=np.zeros((5, 165), dtype=dtype)))
    assert err.value.field == "poses"
    with pytest.raises(InputError) as err:
        load(_amass(tmp_path / "r.npz", mocap_frame_rate=np.array(30, dtype=dtype)))
    assert err.value.field == "mocap_frame_rate"


@pytest.mark.parametrize("meta", [np.array("{not json"), np.array("[1, 2]"),
                                  np.array('{"meta": [1]}'), np.array(3.5),
                                  np.array(b"\xff\xfe{}")],
                         ids=["not-json", "list", "meta-list", "number", "not-utf8"])
def test_malformed_embody_meta_is_one_line_exit_2(tmp_path, capsys, meta):
    path = _amass(tmp_path / "m.npz", embody_meta=meta)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "m.npz: field 'embody_meta'" in err


@pytest.mark.parametrize("meta,field", [
    ({"artifacts": "xyz"}, "artifacts"), ({"gloss": 5}, "gloss"), ({"text": ["a"]}, "text"),
    ({"artifacts": [{"kind": "jitter", "start": "0", "end": 4}]}, "artifacts"),
    ({"seed": True}, "seed"), ({"signs": [{"gloss": 1}]}, "signs")])
def test_mistyped_embody_meta_fields_are_one_line_exit_2(tmp_path, capsys, meta, field):
    path = _amass(tmp_path / "m.npz", embody_meta=np.array(json.dumps({"meta": meta})))
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"m.npz: field 'embody_meta.meta.{field}'" in err, err
    with pytest.raises(InputError) as exc:
        load(path)
    assert exc.value.field == f"embody_meta.meta.{field}"


def test_well_typed_embody_meta_and_unknown_keys_load(tmp_path):
    meta = {"text": "hello", "gloss": ["HELLO"], "seed": 3, "note": {"free": [1, "x"]},
            "artifacts": [{"kind": "jitter", "start": 0, "end": 4, "sigma_rad": 0.1}]}
    path = _amass(tmp_path / "m.npz", embody_meta=np.array(json.dumps({"meta": meta})))
    assert load(path).meta == meta


def test_non_utf8_config_file_is_one_line_exit_2(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(b"io:\n  max_frames: 10 # caf\xe9\n")
    path = _amass(tmp_path / "a.npz")
    assert main(["inspect", str(path), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.yaml" in err and "UTF-8" in err
    assert main(["run", str(tmp_path), "--config", str(cfg), "--store", str(tmp_path / "s")]) == 2
    assert "bad.yaml" in capsys.readouterr().err


@pytest.mark.parametrize("content", [b"{trunc", b"\xff\xfe", b"[]", b'{"sequences": 3}',
                                     b'{"sequences": {"a": {"steps": []}}}'])
def test_corrupt_run_manifest_stops_ls_and_gc(tmp_path, capsys, content):
    store = tmp_path / "store"
    (store / "runs" / "r1").mkdir(parents=True)
    (store / "runs" / "r1" / "manifest.json").write_bytes(content)
    keep = store / "collide" / "ab" / "abcd"
    keep.mkdir(parents=True)
    (keep / "zarr.json").write_text("{}")
    for cmd in (["store", "ls"], ["store", "gc"]):
        assert main([*cmd, "--store", str(store)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "runs/r1/manifest.json" in err
    assert (keep / "zarr.json").exists()  # gc deleted nothing


def test_soke_split_names_outside_poses_are_refused(tmp_path, capsys):
    (tmp_path / "outside").mkdir()
    (tmp_path / "poses" / "ok").mkdir(parents=True)
    split = [{"name": "ok", "text": "a"}, {"name": "../outside", "text": "b"}]
    (tmp_path / "csl_clean.val").write_bytes(gzip.compress(pickle.dumps(split)))
    assert main(["inspect", str(tmp_path), "--split", "val"]) == 2
    err = capsys.readouterr().err
    assert "csl_clean.val: field 'name'" in err and "'../outside'" in err
    assert main(["inspect", str(tmp_path), "--split", "val",
                 "--set", "io.allow_outside_paths=true"]) == 0
    for bad in ("/etc", ""):
        (tmp_path / "csl_clean.val").write_bytes(gzip.compress(pickle.dumps([{"name": bad}])))
        with pytest.raises(InputError):
            load_dataset(tmp_path, "val")


def test_manifest_paths_outside_and_duplicates(tmp_path):
    _amass(tmp_path / "x.npz")
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "m.csv").write_text(f"path,text\n{tmp_path / 'x.npz'},a\n")
    with pytest.raises(InputError, match="line 2: .* is outside the manifest's folder"):
        load_dataset(sub / "m.csv")
    ds = load_dataset(sub / "m.csv", limits=IOConfig(allow_outside_paths=True))
    assert ds[0].path == tmp_path / "x.npz"
    _amass(sub / "a.npz")
    np.save(sub / "a.npy", np.zeros((5, 165)))
    (sub / "d.csv").write_text("path,text\na.npz,x\nb/../a.npz,y\na.npy,z\n")
    with pytest.raises(InputError) as err:
        load_dataset(sub / "d.csv")
    assert err.value.path.endswith("d.csv") and err.value.field == "id"
    assert "'a' (line 4; first on line 2)" in err.value.message


def test_refs_are_absolute_and_load_with_limits(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _amass(tmp_path / "a.npz", t=8)
    (tmp_path / "m.csv").write_text("path,text\na.npz,hi\n")
    ref = load_dataset("m.csv")[0]
    assert isinstance(ref, SequenceRef) and ref.path.is_absolute()
    with pytest.raises(InputError, match="io.max_frames=4"):
        ref.load(limits=IOConfig(max_frames=4))


def test_csv_cells_are_escaped():
    import pandas as pd
    frame = pd.DataFrame({"text": ["=1+1", "+x", "-y", "@z", "plain", None], "n": [-1, 2, 3, 4, 5, 6]})
    out = csv_safe(frame).to_csv(index=False)
    assert "'=1+1" in out and "'+x" in out and "'-y" in out and "'@z" in out
    assert "\nplain," in out and ",-1\n" in out  # text kept, numbers untouched


def test_min_fps_above_max_fps_is_a_config_error(tmp_path, capsys):
    path = _amass(tmp_path / "a.npz")
    assert main(["inspect", str(path), "--set", "io.min_fps=50", "--set", "io.max_fps=10"]) == 2
    assert "io" in capsys.readouterr().err
    assert json.loads(json.dumps(IOConfig().model_dump()))["max_frames"] == 50_000
