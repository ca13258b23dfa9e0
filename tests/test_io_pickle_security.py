"""The pickle loader runs no code: dotted names through numpy submodules are refused in every
pickle-based format, while real numpy arrays in numpy 1.x and 2.x layouts still load."""

from __future__ import annotations

import gzip
import pickle
import struct

import numpy as np
import pytest

from embody.cli import main
from embody.errors import InputError
from embody.io import load, load_dataset
from embody.io.fields import read_pickle

#: numpy submodules that import `os`: a prefix allow-list reaches `os.system` through each.
MODULES = ("numpy.lib._datasource", "numpy.testing._private.utils", "numpy._core._methods")


def _payload(module: str, marker) -> bytes:
    """A protocol-4 pickle calling `module`.`os.system("touch marker")` via STACK_GLOBAL."""
    def s(text: str) -> bytes:
        raw = text.encode()
        return b"\x8c" + bytes([len(raw)]) + raw

    return (b"\x80\x04" + s(module) + s("os.system") + b"\x93" + s(f"touch {marker}")
            + b"\x85R.")


def _in_dict(module: str, key: str, marker) -> bytes:
    """The payload as the value of `key` in a dict, as a real file would carry it."""
    body = _payload(module, marker)[2:-1]  # drop PROTO and STOP
    return b"\x80\x04}" + b"\x8c" + bytes([len(key)]) + key.encode() + body + b"s."


def _signavatars(d, module, marker):
    path = d / "clip.pkl"
    path.write_bytes(_in_dict(module, "smplx", marker))
    return ["inspect", str(path)]


def _soke_frame(d, module, marker):
    seq = d / "poses" / "seq"
    seq.mkdir(parents=True)
    (seq / "000.pkl").write_bytes(_in_dict(module, "smplx_root_pose", marker))
    (seq / "001.pkl").write_bytes(_payload(module, marker))
    return ["inspect", str(seq)]


def _soke_split(d, module, marker):
    (d / "poses" / "seq").mkdir(parents=True)
    (d / "csl_clean.train").write_bytes(gzip.compress(_payload(module, marker)))
    return ["inspect", str(d), "--split", "train"]


@pytest.mark.parametrize("module", MODULES)
@pytest.mark.parametrize("make", [_signavatars, _soke_frame, _soke_split])
def test_dotted_name_bypass_is_refused_in_every_pickle_format(tmp_path, capsys, module, make):
    marker = tmp_path / "pwned"
    argv = make(tmp_path, module, marker)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert not marker.exists()
    assert "refusing to unpickle" in err and "Traceback" not in err


def test_split_bypass_is_refused_by_run_before_anything_starts(tmp_path, capsys):
    marker = tmp_path / "pwned"
    _soke_split(tmp_path, MODULES[0], marker)
    code = main(["run", str(tmp_path), "--split", "train", "--store", str(tmp_path / "store")])
    assert code == 2 and not marker.exists()
    assert "csl_clean.train" in capsys.readouterr().err
    assert not (tmp_path / "store" / "runs").exists()


def test_plain_module_prefix_is_not_enough(tmp_path):
    path = tmp_path / "x.pkl"
    path.write_bytes(pickle.dumps({"smplx": np.lib.format.open_memmap}))
    with pytest.raises(InputError, match="refusing to unpickle numpy.lib"):
        read_pickle(path)


def _numpy1(raw: bytes) -> bytes:
    """A numpy-2 pickle rewritten to numpy 1.x module names (`numpy.core.*`)."""
    count = 0
    for new in ("numpy.core.multiarray", "numpy.core.numeric"):
        old = new.replace("numpy.core", "numpy._core")
        if raw[1] >= 4:  # SHORT_BINUNICODE names, then the frame length shrinks
            a, b = old.encode(), new.encode()
            count += raw.count(b"\x8c" + bytes([len(a)]) + a)
            raw = raw.replace(b"\x8c" + bytes([len(a)]) + a, b"\x8c" + bytes([len(b)]) + b)
        else:  # GLOBAL "module\nname\n"
            raw = raw.replace(old.encode() + b"\n", new.encode() + b"\n")
    if count and raw[2:3] == b"\x95":
        (size,) = struct.unpack("<Q", raw[3:11])
        raw = raw[:3] + struct.pack("<Q", size - count) + raw[11:]
    return raw


@pytest.mark.parametrize("protocol", [2, 4, 5])
@pytest.mark.parametrize("layout", ["numpy2", "numpy1"])
def test_real_numpy_pickles_still_load(tmp_path, protocol, layout):
    rng = np.random.default_rng(0)
    smplx = rng.normal(0, 0.2, (6, 182)).astype(np.float32)
    smplx[:, 179:182] = 0
    data = {"smplx": smplx, "fps": np.float64(24.0), "gender": "neutral",
            "tags": np.array(["a", "b"]), "n": np.int64(6)}
    raw = pickle.dumps(data, protocol=protocol)
    if layout == "numpy1":
        raw = _numpy1(raw)
        assert b"numpy.core" in raw and b"numpy._core" not in raw
    path = tmp_path / "clip.pkl"
    path.write_bytes(raw)
    back = read_pickle(path)
    np.testing.assert_array_equal(back["smplx"], smplx)
    assert back["fps"] == 24.0 and back["n"] == 6 and list(back["tags"]) == ["a", "b"]
    motion = load(path)
    assert motion.num_frames == 6 and motion.fps == 24.0


def test_soke_frames_and_split_in_numpy1_layout_load(tmp_path):
    seq = tmp_path / "poses" / "s1"
    seq.mkdir(parents=True)
    frame = {"smplx_root_pose": np.zeros(3, np.float32), "smplx_body_pose": np.zeros(63, np.float32),
             "smplx_lhand_pose": np.zeros(45), "smplx_rhand_pose": np.zeros(45),
             "smplx_jaw_pose": np.zeros(3), "smplx_shape": np.zeros(10), "cam_trans": np.zeros(3)}
    for i in range(3):
        (seq / f"{i:03d}.pkl").write_bytes(_numpy1(pickle.dumps(frame, protocol=2)))
    split = [{"name": "s1", "text": "hello", "len": np.int64(3)}]
    (tmp_path / "csl_clean.train").write_bytes(gzip.compress(_numpy1(pickle.dumps(split, 4))))
    ds = load_dataset(tmp_path, "train")
    assert ds.ids == ["s1"] and ds[0].load().num_frames == 3
