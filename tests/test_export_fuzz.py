"""Hostile-library fuzzer for `embody export --check` (issue 34).

Seeded: a valid one-sequence library per format is mutated a few hundred ways (library.json
values of the wrong type or value, deleted keys, deep nesting, truncation and byte flips of the
index and of the trajectory file, NaN/inf injection, corrupted rates, symlinks in and out of
the library, huge npz headers, wrong dtypes and shapes, another format's file, a joint moved past
its limits or its velocity limit). Every case must end as the convention says: exit 2 with one
line on stderr, exit 1 with its FAIL rows, or exit 0, and exit 0 only if the library is
genuinely valid by an oracle that shares no code with the check: the consumer's own reader
(numpy, pandas, a plain restricted unpickler), the rate the file states, the robot's limits
and plain MuJoCo contacts between the two hands. Never a traceback.
"""

from __future__ import annotations

import io
import json
import pickle
import shutil
import zipfile
from pathlib import Path

import mujoco
import numpy as np
import pandas as pd
import pytest

from embody.cli import main
from embody.export.library import Trajectory, export_library
from embody.export.formats import BEYONDMIMIC_G1_JOINTS
from embody.robot import load_robot

SEED = 34
CASES = 320
ROBOT = load_robot()
NAMES = tuple(ROBOT.joint_names)
N = len(NAMES)
SUFFIX = {"npz": ".npz", "csv": ".csv", "gmr": ".pkl", "beyondmimic": ".csv"}
ELBOWS = [ROBOT.joint_index(n) for n in ("left_elbow_joint", "right_elbow_joint")]
GARBAGE = [None, -1, 0, 1, 1e308, float("nan"), float("inf"), -0.02, 1e-9, 1e6, "x", "",
           [], {}, True, False, [0.02], {"a": 1}, "../a.npz", "/etc/passwd", "\x1b[31mred",
           "a" * 300, 2 ** 70, 10 ** 400, 5e-324, -0.0, "0.02", [[[[[]]]]]]
RATES = [0.0, -0.02, 1e-9, 1e6, float("nan"), float("inf"), 5e-324, 0.04, 0.0200001, 0.02]


def _valid_q() -> np.ndarray:
    q = np.tile(ROBOT.rest, (30, 1))
    q[:, ELBOWS] = np.linspace(0, 1, 30)[:, None] * np.array([0.2, 0.3])
    return q


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict[str, Path]:
    zero = {"joint_limit_violations": 0, "velocity_violations": 0, "self_collision_frames": 0,
            "torque_viol": 0}
    out = {}
    for fmt in SUFFIX:
        out[fmt] = tmp_path_factory.mktemp(f"valid-{fmt}")
        traj = Trajectory(id="a", robot=ROBOT.name, joint_names=NAMES, q=_valid_q(), dt=0.02,
                          text="t", validation=zero)
        export_library([traj], out[fmt], fmt, robot=ROBOT)
    return out


# -- the oracle: is this library genuinely valid? (no embody code) ---------------------------

class _Plain(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if module.startswith("numpy") and name in ("_reconstruct", "scalar", "ndarray", "dtype"):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name}")


def _hand_contacts(q: np.ndarray) -> int:
    m = ROBOT.model
    d = mujoco.MjData(m)
    names = [m.body(b).name for b in m.geom_bodyid]
    side = np.array([int(n.startswith(("left_wrist", "left_hand")))
                     - int(n.startswith(("right_wrist", "right_hand"))) for n in names])
    hinge = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    adr = m.jnt_qposadr[hinge]
    total = 0
    for qt in q:
        d.qpos[:] = m.qpos0
        d.qpos[adr] = qt
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        g = d.contact.geom[: d.ncon]
        pen = d.contact.dist[: d.ncon] < 0
        total += int((pen & (side[g[:, 0]] * side[g[:, 1]] == -1)).sum())
    return total


def _consumer_read(path: Path, fmt: str, entry: dict, meta: dict) -> tuple[np.ndarray, float]:
    if fmt == "npz":
        with np.load(path) as z:
            return np.asarray(z["q"], np.float64), 1.0 / float(z["dt"])
    if fmt == "csv":
        table = pd.read_csv(path)
        assert list(table.columns) == ["time", *NAMES]
        t = table["time"].to_numpy(np.float64)
        return table[list(NAMES)].to_numpy(np.float64), (len(t) - 1) / (t[-1] - t[0])
    if fmt == "gmr":
        with open(path, "rb") as f:
            motion = _Plain(f).load()
        for key in ("root_pos", "root_rot"):
            assert np.isfinite(np.asarray(motion[key], np.float64)).all()
        return np.asarray(motion["dof_pos"], np.float64), float(motion["fps"])
    rows = np.loadtxt(path, delimiter=",", ndmin=2).astype(np.float32)
    assert np.isfinite(rows).all()
    dt = entry.get("dt")
    rate = 1.0 / dt if dt else (meta.get("rate_hz") or 50.0)
    # BeyondMimic's joints by name, in its order; the rest by the side file's header
    assert rows.shape[1] == 7 + len(BEYONDMIMIC_G1_JOINTS)
    q = np.full((len(rows), N), np.nan)
    q[:, [NAMES.index(n) for n in BEYONDMIMIC_G1_JOINTS]] = rows[:, 7:]
    side = pd.read_csv(path.with_name(path.stem + ".extra_joints.csv"))
    assert len(side) == len(rows)
    q[:, [NAMES.index(n) for n in side.columns]] = side.to_numpy(np.float64).astype(np.float32)
    return q, rate


def _assert_genuinely_valid(lib: Path) -> None:
    meta = json.loads((lib / "library.json").read_text())
    assert not (lib / "library.json").is_symlink()
    for entry in meta["sequences"]:
        path = lib / entry["file"]
        assert path.parent == lib and path.is_file() and not path.is_symlink()
        q, rate = _consumer_read(path, meta["format"], entry, meta)
        assert q.ndim == 2 and q.shape[1] == N and len(q) >= 1
        assert np.isfinite(q).all() and np.isfinite(rate) and 1.0 <= rate <= 1000.0
        if entry.get("dt") is not None:
            assert abs(rate * entry["dt"] - 1.0) < 1e-5
        assert not ((q < ROBOT.lower - 1e-9) | (q > ROBOT.upper + 1e-9)).any()
        vmax = ROBOT.velocity_limits
        assert not (np.abs(np.diff(q, axis=0)) * rate > vmax * (1 + 1e-9) + 1e-9).any()
        assert _hand_contacts(q) == 0


# -- mutations ---------------------------------------------------------------------------------

def _pick(rng, items):
    return items[int(rng.integers(len(items)))]


def _meta(lib: Path) -> dict:
    return json.loads((lib / "library.json").read_text())


def _put_meta(lib: Path, meta) -> None:
    (lib / "library.json").write_text(json.dumps(meta))


def _file(lib: Path) -> Path:
    return lib / f"a{SUFFIX[_meta(lib)['format']]}"


def _rewrite(lib: Path, fmt: str, q: np.ndarray, dt: float = 0.02) -> None:
    path = lib / f"a{SUFFIX[fmt]}"
    t = len(q)
    pos = np.tile(ROBOT.model.qpos0[:3], (t, 1))
    rot = np.tile(ROBOT.model.qpos0[3:7][[1, 2, 3, 0]], (t, 1))
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez(buf, q=q, dt=np.float64(dt), joint_names=np.array(NAMES))
        path.write_bytes(buf.getvalue())
    elif fmt == "csv":
        frame = pd.DataFrame(q, columns=list(NAMES))
        frame.insert(0, "time", np.arange(t) * dt)
        frame.to_csv(path, index=False, float_format="%.17g")
    elif fmt == "gmr":
        path.write_bytes(pickle.dumps({"fps": 1.0 / dt if dt else float("inf"), "root_pos": pos,
                                       "root_rot": rot, "dof_pos": q, "local_body_pos": None,
                                       "link_body_list": None}))
    else:
        np.savetxt(path, np.hstack([pos, rot, q]), delimiter=",", fmt="%.17g")


def m_identity(lib, fmt, rng, tmp):
    pass


def m_entry_value(lib, fmt, rng, tmp):
    meta = _meta(lib)
    meta["sequences"][0][_pick(rng, ["id", "file", "dt", "frames", "written", "text"])] = (
        _pick(rng, GARBAGE))
    _put_meta(lib, meta)


def m_top_value(lib, fmt, rng, tmp):
    meta = _meta(lib)
    meta[_pick(rng, ["format", "robot", "sequences", "rate_hz", "joint_names", "version"])] = (
        _pick(rng, GARBAGE))
    _put_meta(lib, meta)


def m_delete_key(lib, fmt, rng, tmp):
    meta = _meta(lib)
    if rng.random() < 0.5:
        meta.pop(_pick(rng, sorted(meta)))
    else:
        meta["sequences"][0].pop(_pick(rng, sorted(meta["sequences"][0])))
    _put_meta(lib, meta)


def m_deep_json(lib, fmt, rng, tmp):
    depth = int(rng.choice([50, 5_000, 200_000]))
    meta = (lib / "library.json").read_text()
    (lib / "library.json").write_text(meta.replace('"written"', '"deep": ' + "[" * depth
                                                   + "]" * depth + ', "written"', 1))


def _truncate(path: Path, rng) -> None:
    raw = path.read_bytes()
    path.write_bytes(raw[: int(rng.integers(len(raw)))])


def _flip(path: Path, rng) -> None:
    raw = bytearray(path.read_bytes())
    for _ in range(int(rng.integers(1, 6))):
        i = int(rng.integers(len(raw)))
        raw[i] = int(rng.integers(256))
    path.write_bytes(bytes(raw))


def m_truncate_index(lib, fmt, rng, tmp):
    _truncate(lib / "library.json", rng)


def m_flip_index(lib, fmt, rng, tmp):
    _flip(lib / "library.json", rng)


def m_truncate_file(lib, fmt, rng, tmp):
    _truncate(_file(lib), rng)


def m_flip_file(lib, fmt, rng, tmp):
    _flip(_file(lib), rng)


def m_nonfinite(lib, fmt, rng, tmp):
    q = _valid_q()
    bad = _pick(rng, [np.nan, np.inf, -np.inf])
    if rng.random() < 0.3:
        q[:] = bad
    else:
        q[int(rng.integers(len(q))), int(rng.integers(N))] = bad
    _rewrite(lib, fmt, q)


def m_rate(lib, fmt, rng, tmp):
    dt = _pick(rng, RATES)
    if rng.random() < 0.5:
        meta = _meta(lib)
        meta["sequences"][0]["dt"] = dt
        if rng.random() < 0.5:
            meta.pop("rate_hz", None)
        _put_meta(lib, meta)
    else:
        with np.errstate(all="ignore"):
            _rewrite(lib, fmt, _valid_q(), dt)


def m_symlink(lib, fmt, rng, tmp):
    target = _pick(rng, ["outside-copy", "/etc/passwd", "/proc/self/environ", "dangling",
                         "inside", "index"])
    path = _file(lib)
    if target == "index":
        outside = tmp / "library.json"
        shutil.copy(lib / "library.json", outside)
        (lib / "library.json").unlink()
        (lib / "library.json").symlink_to(outside)
        return
    if target == "outside-copy":
        dst = tmp / path.name
        shutil.copy(path, dst)
    elif target == "inside":
        dst = lib / ("b" + path.suffix)
        shutil.copy(path, dst)
    elif target == "dangling":
        dst = tmp / "nowhere"
    else:
        dst = Path(target)
    path.unlink()
    path.symlink_to(dst)


def m_huge_header(lib, fmt, rng, tmp):
    frames = int(rng.choice([50_001, 4_000_000, 10 ** 12]))
    shape = (frames, N) if rng.random() < 0.7 else (frames,)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(head, {"descr": _pick(rng, ["<f8", "<U100000000", "|O"]),
                                                    "fortran_order": False, "shape": shape})
        zf.writestr("q.npy", head.getvalue() + bytes(64))
        sub = io.BytesIO()
        np.save(sub, np.float64(0.02))
        zf.writestr("dt.npy", sub.getvalue())
    _file(lib).write_bytes(buf.getvalue())


def m_wrong_type(lib, fmt, rng, tmp):
    kind = _pick(rng, ["str", "bool", "complex", "narrow", "wide", "3d", "empty", "object"])
    q = _valid_q()
    value = {"str": q.astype(str), "bool": q > 0, "complex": q.astype(complex),
             "narrow": q[:, :-1], "wide": np.hstack([q, q[:, :1]]), "3d": q[:, :, None],
             "empty": q[:0], "object": q.astype(object)}[kind]
    path = _file(lib)
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez(buf, q=value, dt=np.float64(0.02), allow_pickle=True)
        path.write_bytes(buf.getvalue())
    elif fmt == "gmr":
        motion = pickle.loads(path.read_bytes())
        motion[_pick(rng, ["dof_pos", "root_pos", "root_rot", "fps"])] = value
        path.write_bytes(pickle.dumps(motion))
    else:
        flat = value.reshape(len(value), -1) if value.ndim > 1 and len(value) else value
        pd.DataFrame(flat).to_csv(path, index=False, header=(fmt == "csv"))


def m_other_format(lib, fmt, rng, tmp, valid=None):
    other = _pick(rng, [f for f in SUFFIX if f != fmt])
    shutil.copy(valid[other] / f"a{SUFFIX[other]}", _file(lib))


def m_delete_file(lib, fmt, rng, tmp):
    _file(lib).unlink()


def m_unsafe_motion(lib, fmt, rng, tmp):
    """Finite, well-formed, but a robot must not execute it: past a limit or too fast."""
    q = _valid_q()
    j = int(rng.integers(N))
    k = int(rng.integers(1, len(q) - 1))
    if rng.random() < 0.5:
        q[k, j] = ROBOT.upper[j] + 0.05
    else:
        q[k, j] += 2.0 * ROBOT.velocity_limits[j] * 0.02 * (1 if q[k, j] < 0 else -1)
    _rewrite(lib, fmt, q)


MUTATIONS = [m_identity, m_entry_value, m_top_value, m_delete_key, m_deep_json,
             m_truncate_index, m_flip_index, m_truncate_file, m_flip_file, m_nonfinite, m_rate,
             m_symlink, m_huge_header, m_wrong_type, m_other_format, m_delete_file,
             m_unsafe_motion]
#: Mutations after which the library can no longer be valid (exit 0 is a defect outright).
ALWAYS_INVALID = {m_nonfinite, m_symlink, m_huge_header, m_wrong_type, m_delete_file,
                  m_unsafe_motion}


def test_hostile_libraries_end_in_one_line_or_a_verdict_never_a_traceback(valid, tmp_path, capsys):
    rng = np.random.default_rng(SEED)
    seen: dict[str, dict[int, int]] = {}
    for case in range(CASES):
        fmt = _pick(rng, list(SUFFIX))
        mutate = MUTATIONS[case % len(MUTATIONS)] if case < 2 * len(MUTATIONS) else (
            _pick(rng, MUTATIONS))
        work = tmp_path / f"case{case}"
        lib = work / "lib"
        shutil.copytree(valid[fmt], lib)
        (work / "tmp").mkdir()
        if mutate is m_other_format:
            mutate(lib, fmt, rng, work / "tmp", valid=valid)
        else:
            mutate(lib, fmt, rng, work / "tmp")
        capsys.readouterr()
        rc = main(["export", "--check", str(lib)])
        out, err = capsys.readouterr()
        label = f"case {case} {mutate.__name__} {fmt}: rc={rc} out={out[-300:]!r} err={err[-300:]!r}"
        assert "Traceback" not in out + err, label
        assert rc in (0, 1, 2), label
        assert not any(c in out + err for c in "\x1b\r\x00"), label
        if rc == 2:
            assert out == "" and len(err.splitlines()) == 1 and err.startswith("error: "), label
        elif rc == 1:
            assert "FAIL " in out and out.splitlines()[-1].startswith("checked "), label
        else:
            assert mutate not in ALWAYS_INVALID, label
            _assert_genuinely_valid(lib)
        if mutate is m_identity:
            assert rc == 0, label
        seen.setdefault(mutate.__name__, {}).setdefault(rc, 0)
        seen[mutate.__name__][rc] += 1
        shutil.rmtree(work)
    # every mutation ran, and the hostile ones were caught in both ways the gate reports
    assert set(seen) == {m.__name__ for m in MUTATIONS}
    assert seen["m_unsafe_motion"].get(1, 0) > 0 and sum(
        v.get(2, 0) for v in seen.values()) > CASES // 3, seen
