"""Fuzz-style hostile input: 50+ malformed files, generated here from valid ones, through
`inspect` (each one) and `run` (a dataset of them). Every one is exit 2 or an isolated failure,
a single line without a traceback, and nothing partial lands in the store."""

from __future__ import annotations

import gzip
import io
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from embody.cli import main
from embody.store import ArtifactStore

T = 5


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _amass(**over) -> dict:
    base = dict(poses=np.zeros((T, 165)), trans=np.zeros((T, 3)), betas=np.zeros(16),
                gender=np.array("neutral"), mocap_frame_rate=np.array(30.0))
    base.update(over)
    return {k: v for k, v in base.items() if v is not None}


def _signavatars(smplx) -> bytes:
    return pickle.dumps({"smplx": smplx})


def _npy(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _hostile(module: str, name: str, arg: str) -> bytes:
    def s(text: str) -> bytes:
        return b"\x8c" + bytes([len(text)]) + text.encode()
    return b"\x80\x04" + s(module) + s(name) + b"\x93" + s(arg) + b"\x85R."


def _cases(marker: Path) -> dict[str, bytes]:
    """name (with its suffix) → file bytes; every one is malformed or hostile."""
    rng = np.random.default_rng(2026)
    cases: dict[str, bytes] = {}
    valid = {"amass.npz": _npz(**_amass()), "plain.npy": _npy(np.zeros((T, 165))),
             "sa.pkl": _signavatars(np.zeros((T, 182))),
             "arr.npz": _npz(poses=np.zeros((T, 55, 3)), fps=np.array(24.0))}
    for name, raw in valid.items():  # truncations
        stem, suffix = name.split(".")
        for frac in (0.0, 0.05, 0.3, 0.6, 0.95):
            cases[f"trunc{int(frac * 100)}-{stem}.{suffix}"] = raw[: int(len(raw) * frac)]
        cases[f"trunc-last-{stem}.{suffix}"] = raw[:-1]
    bad_values = {  # AMASS npz fields replaced by something wrong
        "nan": _amass(poses=np.full((T, 165), np.nan)),
        "inf-trans": _amass(trans=np.full((T, 3), np.inf)),
        "huge-pose": _amass(poses=np.full((T, 165), 1e30)),
        "huge-trans": _amass(trans=np.full((T, 3), 1e9)),
        "width160": _amass(poses=np.zeros((T, 160))),
        "one-frame": _amass(poses=np.zeros((1, 165)), trans=np.zeros((1, 3))),
        "zero-frames": _amass(poses=np.zeros((0, 165)), trans=np.zeros((0, 3))),
        "3d-poses": _amass(poses=np.zeros((T, 165, 2))),
        "string-poses": _amass(poses=np.array([["a"] * 165] * T)),
        "bool-poses": _amass(poses=np.zeros((T, 165), bool)),
        "complex-poses": _amass(poses=np.zeros((T, 165), complex)),
        "trans-rows": _amass(trans=np.zeros((T + 2, 3))),
        "betas-5": _amass(betas=np.zeros(5)),
        "fps-0": _amass(mocap_frame_rate=np.array(0.0)),
        "fps-neg": _amass(mocap_frame_rate=np.array(-30.0)),
        "fps-nan": _amass(mocap_frame_rate=np.array(np.nan)),
        "fps-tiny": _amass(mocap_frame_rate=np.array(1e-9)),
        "fps-huge": _amass(mocap_frame_rate=np.array(1e9)),
        "fps-text": _amass(mocap_frame_rate=np.array("thirty")),
        "fps-empty": _amass(mocap_frame_rate=np.zeros(0)),
        "no-poses": _amass(poses=None),
        "gender-number": _amass(gender=np.array(3.0)),
        "meta-garbage": _amass(embody_meta=np.array("{{{")),
        "meta-list": _amass(embody_meta=np.array("[]")),
        "meta-zup": _amass(embody_meta=np.array('{"up_axis": "z"}')),
        "meta-bytes": _amass(embody_meta=np.array(b"\xff\xff")),
        "plain-nothing": {"x": np.zeros(3)},
        "plain-two-arrays": {"a": np.zeros((T, 165)), "b": np.zeros((T, 165))},
        "plain-hands": {"poses": np.zeros((T, 165)), "hand_convention": np.array("mixed")},
        "plain-up": {"poses": np.zeros((T, 165)), "up_axis": np.array("x")},
    }
    for name, arrays in bad_values.items():
        cases[f"{name}.npz"] = _npz(**arrays)
    smplx = np.zeros((T, 182))
    pickles = {
        "sa-width": _signavatars(np.zeros((T, 180))),
        "sa-nan": _signavatars(np.where(rng.random((T, 182)) < 0.1, np.nan, smplx)),
        "sa-str": _signavatars("not an array"),
        "sa-fps": pickle.dumps({"smplx": smplx, "fps": -24}),
        "sa-list": pickle.dumps([1, 2, 3]),
        "sa-none": pickle.dumps(None),
        "soke-frame": pickle.dumps({"smplx_root_pose": np.zeros(3)}),
        "os-system": _hostile("os", "system", f"touch {marker}"),
        "builtins-eval": _hostile("builtins", "eval", f"open('{marker}', 'w')"),
        "numpy-dotted": _hostile("numpy.lib._datasource", "os.system", f"touch {marker}"),
        "numpy-getattr": _hostile("numpy", "__builtins__", "x"),
        "gz-bomb-ish": gzip.compress(b"\x80\x04" + b"N" * 1000 + b"."),
        "memo-bomb": gzip.compress(pickle.dumps({"smplx": [[0.0] * 182] * 100_000}, 4)),
        "range-bomb": pickle.dumps({"smplx": range(10 ** 6)}),
        "deep-nesting": (b"\x80\x02}X\x05\x00\x00\x00smplx" + b"(" * 50_000 + b"N"
                         + b"l" * 50_000 + b"s."),
        "ragged-fps": pickle.dumps({"smplx": smplx, "fps": [[24.0, 25.0], [30.0]]}),
        "object-dtype": pickle.dumps({"smplx": smplx.astype(object)}),
    }
    for name, raw in pickles.items():
        cases[f"{name}.pkl"] = raw
    for magic, suffix in ((b"PK\x03\x04", "npz"), (b"\x93NUMPY", "npy"), (b"\x80\x04", "pkl"),
                          (b"\x1f\x8b", "pkl"), (b"", "npz")):
        for i in range(2):
            cases[f"garbage{i}-{suffix}-{len(magic)}.{suffix}"] = magic + rng.bytes(200 + 300 * i)
    header = _npy(np.zeros((T, 165)))[:128]  # a valid npy header promising 10^12 frames
    cases["npy-lies.npy"] = header.replace(b"(5, 165)", b"(1000000000000, 165)")[:128]
    return cases


def test_fuzz_inspect_every_malformed_file_exits_2_in_one_line(tmp_path, capsys):
    marker = tmp_path / "pwned"
    cases = _cases(marker)
    assert len(cases) >= 70
    data = tmp_path / "data"
    data.mkdir()
    for name, raw in cases.items():
        (data / name).write_bytes(raw)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    codes = {}
    for name in cases:
        codes[name] = main(["inspect", str(data / name)])
        err = capsys.readouterr().err.strip()
        assert codes[name] == 2, (name, err)
        assert "Traceback" not in err and len(err.splitlines()) == 1, (name, err)
        assert name in err, (name, err)
    assert not marker.exists()
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # inspect wrote nothing


def test_fuzz_run_isolates_each_bad_file_and_stores_nothing_of_it(prefect_harness, tmp_path,
                                                                  capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "pwned"
    cases = _cases(marker)
    picked = ["trunc60-amass.npz", "nan.npz", "fps-huge.npz", "complex-poses.npz",
              "meta-list.npz", "numpy-dotted.pkl", "sa-width.pkl", "garbage1-npz-4.npz",
              "npy-lies.npy"]
    data = tmp_path / "data"
    data.mkdir()
    for name in picked:
        (data / name).write_bytes(cases[name])
    np.savez(data / "good.npz", **_amass(poses=np.random.default_rng(0).normal(0, .1, (T, 165))))
    store = tmp_path / "store"
    code = main(["run", str(data), "--store", str(store), "--name", "fuzz", "--critic", "none",
                 "--no-render", "--set", "collision.enabled=false", "--set", "ik.iterations=1",
                 "--set", "ik.shape_iterations=10", "--json", "--no-progress"])
    out = capsys.readouterr()
    assert code == 1, out.err
    summary = json.loads(out.out)
    assert (summary["ok"], summary["failed"]) == (1, len(picked))
    assert "Traceback" not in out.err and not marker.exists()
    manifest = json.loads(Path(summary["manifest"]).read_text())
    for name in picked:
        seq = manifest["sequences"][Path(name).with_suffix("").as_posix()]
        assert seq["status"] == "failed" and seq["failed_step"] == "source"
        assert seq["steps"] == {} and "\n" not in seq["error"]
        assert name in seq["error"]
    st = ArtifactStore(store)
    sources = [k for step, k, _ in st.entries() if step == "source"]
    assert sources == [manifest["sequences"]["good"]["steps"]["source"]]
    assert not list(store.rglob("*.tmp")) and not st.stale_temps()
