"""`embody export --check` is a safety gate and `embody export` writes whole files (issue 34).

Each case here passed `--check`, crashed it, or corrupted files before: NaN trajectories, a rate
taken from library.json instead of the file, unbounded reads, paths and symlinks leaving the
library, malformed indexes, control characters echoed, writes through a planted symlink and
truncated files after a full disk.
"""

from __future__ import annotations

import errno
import io
import json
import os
import pickle
import shutil
import subprocess
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from embody.cli import main
from embody.config.io import IOConfig
from embody.errors import EmbodyError, InputError
from embody.export.library import Trajectory, check_library, export_library
from embody.export.formats import beyondmimic_columns
from embody.robot import load_robot

ROBOT = load_robot()
NAMES = tuple(ROBOT.joint_names)
ELBOW = ROBOT.joint_index("left_elbow_joint")
SUFFIX = {"npz": ".npz", "csv": ".csv", "gmr": ".pkl", "beyondmimic": ".csv"}
FORMATS = tuple(SUFFIX)


def _q(frames: int = 30) -> np.ndarray:
    """Forearms rising slowly, apart: valid (limits, velocities, no contact) at 50 Hz."""
    q = np.tile(ROBOT.rest, (frames, 1))
    q[:, [ELBOW, ROBOT.joint_index("right_elbow_joint")]] = (
        np.linspace(0, 1, frames)[:, None] * np.array([0.2, 0.3]))
    return q


def _traj(sid: str = "a", q: np.ndarray | None = None, dt: float = 0.02) -> Trajectory:
    zero = {"joint_limit_violations": 0, "velocity_violations": 0, "self_collision_frames": 0,
            "torque_viol": 0}
    return Trajectory(id=sid, robot=ROBOT.name, joint_names=NAMES, q=_q() if q is None else q,
                      dt=dt, text="t", validation=zero)


@pytest.fixture(scope="module")
def libraries(tmp_path_factory) -> dict[str, Path]:
    out = {}
    for fmt in FORMATS:
        out[fmt] = tmp_path_factory.mktemp(fmt)
        library, _ = export_library([_traj()], out[fmt], fmt, robot=ROBOT)
        assert library["id"].tolist() == ["a"]
    return out


@pytest.fixture
def lib(libraries, request, tmp_path) -> Path:
    """A fresh copy of the valid one-sequence library in the test's format."""
    dst = tmp_path / "lib"
    shutil.copytree(libraries[request.param], dst)
    return dst


def _check(path: Path, capsys) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["export", "--check", str(path)])
    out, err = capsys.readouterr()
    return rc, out, err


def _refused(path: Path, capsys, *words: str) -> str:
    """--check exits 2 with one line on stderr naming the file; returns that line."""
    rc, out, err = _check(path, capsys)
    assert rc == 2, (rc, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in out + err
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


def _meta(lib: Path) -> dict:
    return json.loads((lib / "library.json").read_text())


def _set_meta(lib: Path, meta: dict) -> None:
    (lib / "library.json").write_text(json.dumps(meta))


def _npz(path: Path, **arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())


def _write_raw(lib: Path, fmt: str, q: np.ndarray, *, dt: float = 0.02, root_pos=None,
               root_xyzw=None, time=None) -> Path:
    """The sequence's file rewritten the way an outside tool would (numpy, pandas-free)."""
    path = lib / f"a{SUFFIX[fmt]}"
    t = len(q)
    root_pos = np.tile(ROBOT.model.qpos0[:3], (t, 1)) if root_pos is None else root_pos
    root_xyzw = (np.tile(ROBOT.model.qpos0[3:7][[1, 2, 3, 0]], (t, 1)) if root_xyzw is None
                 else root_xyzw)
    if fmt == "npz":
        _npz(path, q=q, dt=np.float64(dt), joint_names=np.array(NAMES))
    elif fmt == "csv":
        time = np.arange(t) * dt if time is None else time
        rows = np.column_stack([time, q])
        path.write_text(",".join(["time", *NAMES]) + "\n"
                        + "\n".join(",".join(f"{v:.17g}" for v in r) for r in rows) + "\n")
    elif fmt == "gmr":
        path.write_bytes(pickle.dumps({"fps": 1.0 / dt, "root_pos": root_pos, "root_rot": root_xyzw,
                                       "dof_pos": q, "local_body_pos": None,
                                       "link_body_list": None}))
    else:  # BeyondMimic's 29 G1 joints in its order, the fingers in the side file
        main, extra = beyondmimic_columns(NAMES)
        np.savetxt(path, np.hstack([root_pos, root_xyzw, q[:, main]]), delimiter=",", fmt="%.17g")
        np.savetxt(lib / "a.extra_joints.csv", q[:, extra], delimiter=",", fmt="%.17g",
                   comments="", header=",".join(NAMES[i] for i in extra))
    return path


@pytest.mark.parametrize("lib", FORMATS, indirect=True)
def test_a_valid_library_passes_and_its_rewrite_too(lib, capsys):
    rc, out, _ = _check(lib, capsys)
    assert rc == 0 and out.startswith("ok   a:")
    fmt = _meta(lib)["format"]
    _write_raw(lib, fmt, _q())  # the same trajectory written by another tool
    assert _check(lib, capsys)[0] == 0


# 1. non-finite values anywhere ---------------------------------------------------------------

@pytest.mark.parametrize("lib", FORMATS, indirect=True)
@pytest.mark.parametrize("where", ["all", "one"])
def test_nan_joints_fail(lib, where, capsys):
    fmt = _meta(lib)["format"]
    q = _q()
    if where == "all":
        q[:] = np.nan
    else:
        q[7, ELBOW] = np.inf
    _write_raw(lib, fmt, q)
    _refused(lib, capsys, "non-finite", f"a{SUFFIX[fmt]}")


@pytest.mark.parametrize("lib", ["gmr", "beyondmimic"], indirect=True)
@pytest.mark.parametrize("part", ["root_pos", "root_rot"])
def test_nan_or_broken_root_pose_fails(lib, part, capsys):
    fmt = _meta(lib)["format"]
    pos = np.tile(ROBOT.model.qpos0[:3], (30, 1))
    rot = np.tile(ROBOT.model.qpos0[3:7][[1, 2, 3, 0]], (30, 1))
    (pos if part == "root_pos" else rot)[3] = np.nan
    _write_raw(lib, fmt, _q(), root_pos=pos, root_xyzw=rot)
    _refused(lib, capsys, "non-finite")
    rot = np.tile([0.0, 0.0, 0.0, 3.0], (30, 1))  # finite, but not a rotation
    _write_raw(lib, fmt, _q(), root_xyzw=rot)
    _refused(lib, capsys, "unit quaternion")


def test_export_refuses_nan_instead_of_writing_it(tmp_path):
    q = _q()
    q[3, ELBOW] = np.nan
    library, excluded = export_library([_traj("a"), _traj("n", q)], tmp_path, "npz", robot=ROBOT)
    assert library["id"].tolist() == ["a"]
    assert "non-finite" in excluded.set_index("id").loc["n", "reason"]
    assert not (tmp_path / "n.npz").exists()


# 2. the rate comes from the file ----------------------------------------------------------------

def _jumping() -> np.ndarray:
    """The elbow jumps 1.5× its velocity limit every 20 ms, within its range."""
    q = _q()
    step = 1.5 * ROBOT.velocity_limits[ELBOW] * 0.02
    q[:, ELBOW] = ROBOT.lower[ELBOW] + 0.2 + step * (np.arange(30) % 2)
    assert q[:, ELBOW].max() < ROBOT.upper[ELBOW]
    return q


@pytest.mark.parametrize("lib", FORMATS, indirect=True)
def test_a_50hz_file_jumping_past_the_velocity_limit_fails_whatever_library_json_says(lib, capsys):
    fmt = _meta(lib)["format"]
    _write_raw(lib, fmt, _jumping())
    rc, out, _ = _check(lib, capsys)
    assert rc == 1 and "FAIL a" in out and "velocity_violations=29" in out
    for dt in (1e6, -0.02, 0.0, float("nan"), 5e-324, 10 ** 400, "0.02", True):
        meta = _meta(lib)
        meta["sequences"][0]["dt"] = dt
        meta.pop("rate_hz", None)
        _set_meta(lib, meta)
        rc, out, err = _check(lib, capsys)
        assert rc in (1, 2) and "Traceback" not in err, (dt, rc, out, err)
        if rc == 2:
            assert len(err.strip().splitlines()) == 1 and ("dt" in err or "rate" in err), err
        else:
            assert "velocity_violations=29" in out, (dt, out)
    if fmt == "beyondmimic":  # states no rate: library.json's is the rate, and must be sane
        return
    meta = _meta(lib)
    meta["sequences"][0]["dt"] = 1e6
    _set_meta(lib, meta)
    _refused(lib, capsys, "rate", "library.json")


@pytest.mark.parametrize("lib", ["npz", "csv", "gmr"], indirect=True)
@pytest.mark.parametrize("dt", [1e6, 1e-9])
def test_the_files_own_rate_must_be_sane(lib, dt, capsys):
    """File and library.json agree on an absurd rate: refused (io.min_fps..io.max_fps)."""
    fmt = _meta(lib)["format"]
    _write_raw(lib, fmt, _jumping(), dt=dt)
    meta = _meta(lib)
    meta["sequences"][0]["dt"] = dt
    meta.pop("rate_hz")
    _set_meta(lib, meta)
    _refused(lib, capsys, "io.min_fps")


@pytest.mark.parametrize("lib", ["npz", "gmr"], indirect=True)
@pytest.mark.parametrize("rate", [0.0, -50.0, float("nan"), float("inf")])
def test_a_zero_negative_or_nan_rate_in_the_file_fails(lib, rate, capsys):
    fmt = _meta(lib)["format"]
    path = lib / f"a{SUFFIX[fmt]}"
    if fmt == "npz":
        _npz(path, q=_q(), dt=np.float64(1.0 / rate if rate else 0.0), joint_names=np.array(NAMES))
    else:
        motion = pickle.loads(path.read_bytes())
        motion["fps"] = rate
        path.write_bytes(pickle.dumps(motion))
    _refused(lib, capsys)


@pytest.mark.parametrize("lib", ["csv"], indirect=True)
def test_csv_time_must_be_even_and_increasing(lib, capsys):
    time = np.arange(30) * 0.02
    time[10:] += 0.5
    _write_raw(lib, "csv", _q(), time=time)
    _refused(lib, capsys, "time")


# 3. bounded reads --------------------------------------------------------------------------------

def _over_limit_npz(path: Path, frames: int) -> None:
    """A valid npz of `frames` zero frames, written without holding it: headers, then zeros."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("q.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_1_0(
                fh, {"descr": "<f8", "fortran_order": False, "shape": (frames, len(NAMES))})
            row = bytes(8 * len(NAMES) * 1000)
            for _ in range(frames // 1000):
                fh.write(row)
        sub = io.BytesIO()
        np.save(sub, np.float64(0.02))
        zf.writestr("dt.npy", sub.getvalue())
    path.write_bytes(buf.getvalue())


@pytest.mark.parametrize("lib", ["npz"], indirect=True)
def test_a_small_npz_claiming_millions_of_frames_is_refused_from_its_header(lib, capsys):
    _over_limit_npz(lib / "a.npz", 2_000_000)  # 688 MB of float64 in a ~0.7 MB file
    assert (lib / "a.npz").stat().st_size < 2_000_000
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="io.max_frames"):
            check_library(lib, ROBOT)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, peak
    _refused(lib, capsys, "io.max_frames")


@pytest.mark.parametrize("lib", ["csv", "beyondmimic", "gmr"], indirect=True)
def test_files_over_the_frame_or_size_bound_are_refused_before_parsing(lib):
    fmt = _meta(lib)["format"]
    _write_raw(lib, fmt, _q(200))
    meta = _meta(lib)
    meta["sequences"][0]["frames"] = 200
    _set_meta(lib, meta)
    assert check_library(lib, ROBOT)["ok"].tolist() == [True]
    with pytest.raises(InputError, match="io.max_frames|bytes"):
        check_library(lib, ROBOT, IOConfig(max_frames=100))
    # a file bigger than io.max_frames rows of text can be is refused from its size alone
    path = lib / f"a{SUFFIX[fmt]}"
    path.write_bytes(path.read_bytes() + b" " * (2 << 20))
    with pytest.raises(InputError, match="bytes"):
        check_library(lib, ROBOT, IOConfig(max_frames=2))


@pytest.mark.parametrize("lib", ["csv"], indirect=True)
def test_a_csv_of_many_rows_is_refused_while_streaming(lib, capsys):
    path = lib / "a.csv"
    line = (",".join(["0.02"] + ["0"] * len(NAMES)) + "\n").encode()
    with open(path, "wb") as fh:
        fh.write((",".join(["time", *NAMES]) + "\n").encode())
        fh.write(line * 60_000)  # more than io.max_frames = 50,000 rows, < the size bound
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="io.max_frames"):
            check_library(lib, ROBOT)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, peak


@pytest.mark.parametrize("lib", ["csv", "beyondmimic"], indirect=True)
@pytest.mark.parametrize("where", ["first", "last"])
def test_a_csv_line_longer_than_a_row_is_refused_before_parsing(lib, where):
    """One 8 MB line of a million fields (a parser would hold a million strings)."""
    path = lib / f"a{SUFFIX[_meta(lib)['format']]}"
    lines = path.read_bytes().splitlines(keepends=True)
    lines[0 if where == "first" else -1] = b",".join([b"1e-5"] * 1_000_000) + b"\n"
    path.write_bytes(b"".join(lines))
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="longer than"):
            check_library(lib, ROBOT)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5e6, peak


@pytest.mark.parametrize("lib", ["npz"], indirect=True)
def test_a_huge_library_json_or_a_fifo_is_refused_unread(lib, capsys):
    (lib / "a.npz").unlink()
    os.mkfifo(lib / "a.npz")  # opening it for reading would block forever
    _refused(lib, capsys, "not a regular file")
    meta = _meta(lib)
    meta["padding"] = "x" * (65 << 20)
    _set_meta(lib, meta)
    _refused(lib, capsys, "library.json", "bytes")


# 4. paths stay inside the library; export never writes through a symlink -----------------------

@pytest.mark.parametrize("lib", FORMATS, indirect=True)
def test_symlinks_and_paths_out_of_the_library_are_refused(lib, tmp_path, capsys):
    fmt = _meta(lib)["format"]
    name = f"a{SUFFIX[fmt]}"
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.move(lib / name, outside / name)  # a valid file, outside the library
    (lib / name).symlink_to(outside / name)
    _refused(lib, capsys, "symbolic link")
    (lib / name).unlink()
    for bad in (f"../outside/{name}", str(outside / name), "..", "/etc/passwd", "a\x1b[2Jb"):
        meta = _meta(lib)
        meta["sequences"][0]["file"] = bad
        _set_meta(lib, meta)
        line = _refused(lib, capsys, "sequences[0].file")
        assert "\x1b" not in line
    shutil.move(lib / "library.json", outside / "library.json")
    (lib / "library.json").symlink_to(outside / "library.json")
    _refused(lib, capsys, "symbolic link")


@pytest.mark.parametrize("fmt", FORMATS)
def test_export_replaces_a_planted_symlink_instead_of_writing_through_it(tmp_path, fmt):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    for name in (f"a{SUFFIX[fmt]}", "library.json", "library.csv", "excluded.csv"):
        (out / name).symlink_to(victim)
    library, _ = export_library([_traj()], out, fmt, robot=ROBOT)
    assert library["id"].tolist() == ["a"]
    assert victim.read_text() == "precious"
    for name in (f"a{SUFFIX[fmt]}", "library.json", "library.csv", "excluded.csv"):
        assert (out / name).is_file() and not (out / name).is_symlink()
    assert check_library(out)["ok"].tolist() == [True]


# 5. every malformed library is one line and exit 2 ------------------------------------------------

def _deep(n: int) -> str:
    return "[" * n + "]" * n


MALFORMED = {
    "entry-without-id": lambda m: m["sequences"][0].pop("id"),
    "entry-without-file": lambda m: m["sequences"][0].pop("file"),
    "entry-not-a-dict": lambda m: m.__setitem__("sequences", [5]),
    "entry-id-a-list": lambda m: m["sequences"][0].__setitem__("id", ["a"]),
    "file-a-number": lambda m: m["sequences"][0].__setitem__("file", 3),
    "written-a-string": lambda m: m["sequences"][0].__setitem__("written", "xyz"),
    "frames-a-string": lambda m: m["sequences"][0].__setitem__("frames", "30"),
    "sequences-a-dict": lambda m: m.__setitem__("sequences", {"a": 1}),
    "sequences-missing": lambda m: m.pop("sequences"),
    "format-unknown": lambda m: m.__setitem__("format", "\x1b[31mexe"),
    "format-a-list": lambda m: m.__setitem__("format", ["npz"]),
    "robot-dotdot": lambda m: m.__setitem__("robot", "../../etc/x"),
    "robot-unknown": lambda m: m.__setitem__("robot", "no_such_robot"),
    "robot-a-dict": lambda m: m.__setitem__("robot", {"name": "x"}),
    "robot-missing": lambda m: m.pop("robot"),
    "joint-names-differ": lambda m: m.__setitem__("joint_names", ["x"]),
    "rate-a-string": lambda m: m.__setitem__("rate_hz", "50"),
    "rate-disagrees": lambda m: m.__setitem__("rate_hz", 25.0),
}


@pytest.mark.parametrize("lib", ["npz"], indirect=True)
@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_index_is_one_line_exit_2(lib, case, capsys):
    meta = _meta(lib)
    MALFORMED[case](meta)
    _set_meta(lib, meta)
    line = _refused(lib, capsys, "library.json")
    assert "\x1b" not in line


@pytest.mark.parametrize("lib", ["npz"], indirect=True)
def test_a_path_like_robot_option_is_one_line(lib, capsys):
    capsys.readouterr()
    rc = main(["export", "--check", str(lib), "--robot", "../../etc/x"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--robot" in err, err


@pytest.mark.parametrize("lib", ["npz"], indirect=True)
@pytest.mark.parametrize("text", [_deep(100_000), "[1, 2]", "{", "\xff\xfe".encode("latin1"),
                                  '{"format": "npz", "robot": "unitree_g1_dex3", "sequences": '
                                  + _deep(50_000) + "}"])
def test_unreadable_index_is_one_line_exit_2(lib, text, capsys):
    (lib / "library.json").write_bytes(text if isinstance(text, bytes) else text.encode())
    _refused(lib, capsys, "library.json")


@pytest.mark.parametrize("lib", FORMATS, indirect=True)
@pytest.mark.parametrize("cut", [0, 0.1, 0.5, 0.9, -1])
def test_truncated_files_are_one_line_exit_2(lib, cut, capsys):
    fmt = _meta(lib)["format"]
    path = lib / f"a{SUFFIX[fmt]}"
    raw = path.read_bytes()
    path.write_bytes(raw[:-1] if cut == -1 else raw[: int(len(raw) * cut)])
    rc, out, err = _check(lib, capsys)
    if fmt in ("csv", "beyondmimic") and cut == -1:  # only the last line break is gone
        assert rc == 0
        return
    if fmt in ("csv", "beyondmimic") and cut != 0:
        # a csv cut at a line break is a shorter, valid trajectory; the index's frame count differs
        assert rc in (1, 2) and "Traceback" not in err
        if rc == 1:
            assert "frames, library.json says 30" in out
        return
    _refused(lib, capsys)


# 6. control characters are not echoed -------------------------------------------------------------

@pytest.mark.parametrize("lib", ["npz"], indirect=True)
def test_ids_are_printed_without_control_characters(lib, capsys):
    meta = _meta(lib)
    meta["sequences"][0]["id"] = "\x1b[2J\x1b[31mevil\nok   forged: all fine\r"
    _set_meta(lib, meta)
    rc, out, err = _check(lib, capsys)
    assert rc == 0
    assert "\x1b" not in out and "\r" not in out
    assert out.count("\n") == 2 and "\\x1b[31mevil\\nok" in out


# 7. export writes whole files: a full disk leaves nothing truncated ----------------------------------

@pytest.mark.parametrize("share", [0.0, 0.1, 0.5, 0.9, 0.999, 1.0])
def test_a_full_disk_during_export_leaves_no_partial_file(tmp_path, monkeypatch, share):
    """The disk fills after `share` of the library's bytes (os.write is the OS's write: an
    outside fault); share 1.0 is room for all of it."""
    trajs = [_traj(s) for s in ("a", "b", "c")]
    whole = tmp_path / "whole"
    export_library(trajs, whole, "csv", robot=ROBOT)
    total = sum(p.stat().st_size for p in whole.iterdir())
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    real_write = os.write
    left = [int(total * share)]

    def write(fd: int, data) -> int:
        n = min(len(data), left[0])
        if n == 0 and len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        left[0] -= n
        return real_write(fd, bytes(data[:n]))

    monkeypatch.setattr(os, "write", write)
    try:
        library, _ = export_library(trajs, out, "csv", robot=ROBOT)
    except EmbodyError as exc:
        assert "no space left on device" in str(exc) and str(out) in str(exc)
        assert share < 1.0 and sorted(p.name for p in out.iterdir()) == ["mine.txt"]
        return
    finally:
        monkeypatch.undo()
    assert share == 1.0 and library["id"].tolist() == ["a", "b", "c"]
    assert check_library(out, ROBOT)["ok"].all()


def test_an_export_that_stops_midway_removes_what_it_wrote(tmp_path):
    """The third trajectory is for another robot (InputError): the first two files go too."""
    other = Trajectory(id="c", robot=ROBOT.name, joint_names=NAMES[::-1], q=_q(), dt=0.02,
                       validation=_traj().validation)
    with pytest.raises(InputError, match="joint_names"):
        export_library([_traj("a"), _traj("b"), other], tmp_path, "npz", robot=ROBOT)
    assert list(tmp_path.iterdir()) == []


def _mount_tmpfs(folder: Path, size: str) -> bool:
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    folder.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True)
    return done.returncode == 0


def test_a_real_full_disk_leaves_no_partial_file(tmp_path):
    """On a 64 KiB tmpfs (root only; skipped elsewhere) the export fails whole."""
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "64k"):
        pytest.skip("needs root and tmpfs to mount a small disk")
    try:
        with pytest.raises(EmbodyError, match="no space left on device"):
            export_library([_traj(s, _q(150)) for s in "abcdefgh"], disk, "csv", robot=ROBOT)
        assert list(disk.iterdir()) == []
    finally:
        subprocess.run(["umount", str(disk)], check=False)
